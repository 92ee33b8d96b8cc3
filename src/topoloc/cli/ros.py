"""``topoloc ros-node``: the ROS 1 node (:mod:`topoloc.ros.node`) from the command line."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from topoloc.cli.app import app, handle_errors, needs
from topoloc.cli.options import LocalizeSequenceOption, PrefetchOption, QuietOption, VerifyOption


@app.command("ros-node", cls=needs(), context_settings={"allow_extra_args": True, "ignore_unknown_options": True})
@handle_errors
def ros_node(
    ctx: typer.Context,
    map_file: Annotated[str | None, typer.Argument(
        help="Map file (topoloc map build); default the private parameter ~map.")] = None,
    image_topic: Annotated[str | None, typer.Option(
        help="Image topic (sensor_msgs/Image or CompressedImage); default ~image_topic, else 'image' (remap "
             "it: image:=/camera/image_raw).")] = None,
    sequence: LocalizeSequenceOption = None,
    sequence_mode: Annotated[str | None, typer.Option(
        help="constant or acceleration (with --sequence); default ~sequence_mode, else the map's.")] = None,
    queue: Annotated[int | None, typer.Option(
        help="Frames that may wait to be matched, older ones skipped and counted; default ~queue, else 1 "
             "(the newest frame only).")] = None,
    rate: Annotated[float | None, typer.Option(
        help="At most this many frames localised a second (the others skipped); default ~rate, else 0 "
             "(as fast as the cores allow).")] = None,
    top_k: Annotated[int | None, typer.Option(help="Places listed per answer; default ~top_k, else 5.")] = None,
    prefetch: PrefetchOption = -1,
    map_frame: Annotated[str | None, typer.Option(
        help="frame_id of ~position (the map's coordinates); default ~map_frame, else 'map'.")] = None,
    no_watch_map: Annotated[bool, typer.Option(
        "--no-watch-map", help="Do not reload the map when its file changes (default: ~watch_map, else reload); "
                               "SIGHUP and the ~reload service still reload it.")] = False,
    verify: VerifyOption = None,
    quiet: QuietOption = False,
) -> None:
    """Localise an image topic on a running ROS 1 graph: answers on ~answer, positions on ~position.

    Options given here win over the node's private parameters (~map, ~image_topic, ~sequence, ~queue,
    ~rate, ~verify, ...). ROS arguments (remappings such as image:=/camera/image_raw, __name:=...) are passed to
    ROS. --prefetch defaults to one frame per core here (each frame ahead adds a frame's time to the
    latency). Needs ROS 1's rospy from the system (docs/ros.md). Stops on SIGINT/SIGTERM (exit 0) or when the
    ROS master is gone (exit 1), with one line.
    """
    from topoloc.errors import TopolocError
    from topoloc.ros.node import serve

    args = list(ctx.args)
    if map_file is not None and ":=" in map_file:  # no map given: the first ROS argument took its place
        args.insert(0, map_file)
        map_file = None
    ros_args = [a for a in args if ":=" in a]
    unknown = [a for a in args if ":=" not in a]
    if unknown:
        raise TopolocError(f"unknown argument {unknown[0]!r} (ROS remappings are NAME:=VALUE)")
    prefetch_given = getattr(ctx.get_parameter_source("prefetch"), "name", None) != "DEFAULT"
    given = {"map": None if map_file is None else Path(map_file), "image_topic": image_topic, "sequence": sequence,
             "sequence_mode": sequence_mode, "queue": queue, "rate": rate, "top_k": top_k, "map_frame": map_frame,
             "watch_map": False if no_watch_map else None, "prefetch": prefetch if prefetch_given else None,
             "verify": verify}
    status = serve(given, ros_args)
    if status:
        raise typer.Exit(code=status)
