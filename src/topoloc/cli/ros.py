"""``topoloc ros-node`` (ROS 1) and ``topoloc ros2-node`` (ROS 2): one command, the node's settings as options.

Each option is a parameter of :class:`topoloc.spec.NodeSpec` under its flat
name (``--image-topic`` is the parameter ``image_topic``); an option given wins
over the node's ROS parameter, which wins over ``--config FILE``.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any

import typer

from topoloc.cli.app import app, handle_errors, needs
from topoloc.cli.options import ConfigOption, LocalizeSequenceOption, QuietOption, VerifyOption

ROS1_HELP = """Localise an image topic on a running ROS 1 graph: answers on ~answer, positions on ~position.

Options given here win over the node's private parameters (~map, ~image_topic, ~sequence, ~queue, ~rate,
~verify, ...), which win over --config. ROS arguments (remappings such as image:=/camera/image_raw,
__name:=...) are passed to ROS. Needs ROS 1's rospy from the system (docs/ros.md). Stops on SIGINT/SIGTERM
(exit 0) or when the ROS master is gone (exit 1), with one line.
"""

ROS2_HELP = """Localise an image topic on ROS 2: answers on answer, positions on position (under the namespace).

Options given here win over the node's parameters (--ros-args -p queue:=2, --params-file), which win over
--config; the parameters can be changed while it runs (ros2 param set; device cannot). ROS 2's arguments
follow --ros-args (-r image:=/camera/image_raw, -r __ns:=/robot, -p map:=route.tlm). Needs rclpy: pip
install 'topoloc[ros2]' (docs/ros.md). Stops on SIGINT/SIGTERM (exit 0) with one line.
"""

#: ROS 2 arguments that take a value (after --ros-args), which the command line might take for MAP.
_ROS2_VALUE_FLAGS = ("-r", "--remap", "-p", "--param", "--params-file", "-e", "--enclave", "--log-level",
                     "--log-config-file")


def node_command(
    ctx: typer.Context,
    map_file: Annotated[str | None, typer.Argument(
        help="Map file (topoloc map build); default the node's parameter map.")] = None,
    image_topic: Annotated[str | None, typer.Option(
        help="Image topic (sensor_msgs/Image or CompressedImage); default the parameter image_topic, else "
             "'image' (remap it).")] = None,
    sequence: LocalizeSequenceOption = None,
    sequence_mode: Annotated[str | None, typer.Option(
        help="constant or acceleration (with --sequence); default as the map was calibrated.")] = None,
    queue: Annotated[int | None, typer.Option(
        help="Frames that may wait to be matched, older ones skipped and counted; default 1 (the newest "
             "frame only).")] = None,
    rate: Annotated[float | None, typer.Option(
        help="At most this many frames localised a second (the others skipped); default 0 (as fast as the "
             "cores allow).")] = None,
    top_k: Annotated[int | None, typer.Option(help="Places listed per answer; default 5.")] = None,
    prefetch: Annotated[int | None, typer.Option(
        help="Frames decoded and described ahead while one is matched; default one per core (each frame "
             "ahead adds a frame's time to the latency).")] = None,
    map_frame: Annotated[str | None, typer.Option(
        help="frame_id of the positions (the map's coordinates); default 'map'.")] = None,
    watch_map: Annotated[bool | None, typer.Option(
        "--watch-map/--no-watch-map", help="Reload the map when its file changes (default: reload); the reload "
                                           "service and SIGHUP reload it either way.")] = None,
    verify: VerifyOption = None,
    verify_candidates: Annotated[int | None, typer.Option(
        help="Distinct peaks verified per frame (default: as localize).")] = None,
    min_support: Annotated[int | None, typer.Option(
        "--min-support", help="Support (inliers that are distinctive matches) a verified answer needs "
                              "(default: as localize).")] = None,
    confirm: Annotated[bool | None, typer.Option(
        "--confirm/--no-confirm", help="Temporal consistency of the answers (default off).")] = None,
    config: ConfigOption = None,
    quiet: QuietOption = False,
) -> None:
    from topoloc.errors import TopolocError
    from topoloc.spec import NodeSpec

    values = {"map": map_file, "image_topic": image_topic, "sequence": sequence, "sequence_mode": sequence_mode,
              "queue": queue, "rate": rate, "top_k": top_k, "prefetch": prefetch, "map_frame": map_frame,
              "watch_map": watch_map, "verify": verify, "verify_candidates": verify_candidates,
              "min_support": min_support, "confirm": confirm,
              "device": None}  # topoloc --device (before the command) sets it for the process, as for every command
    assert set(values) == set(NodeSpec.PARAMS)  # every parameter is an option, under its own name
    if map_file is not None and map_file.startswith("-") and map_file != "--ros-args":
        # Unknown options reach here as arguments (ROS's own must pass through): a flag in MAP's place is none.
        raise TopolocError(f"no such option: {map_file} (see '{ctx.command_path} --help')")
    if ctx.info_name == "ros2-node":
        from topoloc.ros.node2 import serve as serve2

        map_file, ros_args = _ros2_arguments(map_file, list(ctx.args))
        values["map"] = None if map_file is None else str(Path(map_file))
        status = serve2(values, ros_args, config=config)
    else:
        from topoloc.ros.node import serve

        args = list(ctx.args)
        if map_file is not None and ":=" in map_file:  # no map given: the first ROS argument took its place
            args.insert(0, map_file)
            values["map"] = None
        ros_args = [a for a in args if ":=" in a]
        unknown = [a for a in args if ":=" not in a]
        if unknown:
            raise TopolocError(f"unknown argument {unknown[0]!r} (ROS remappings are NAME:=VALUE)")
        status = serve(values, ros_args, config=config)
    if status:
        raise typer.Exit(code=status)


def _ros2_arguments(map_file: str | None, args: list[str]) -> tuple[str | None, list[str]]:
    """The map and ROS 2's arguments (``--ros-args ...``), however the command line split them.

    The command line takes the first word that is no option for MAP, which may
    be a ROS 2 argument's value (``--ros-args -r image:=/cam``): the process's
    own arguments tell where ROS 2's begin.
    """
    from topoloc.errors import TopolocError

    argv = sys.argv[1:]
    if "--ros-args" in argv:
        ros = argv[argv.index("--ros-args"):]
        if map_file is not None and map_file not in argv[:argv.index("--ros-args")]:
            map_file = None  # it was a value of ROS 2's arguments
        return map_file, ros
    if not args:
        return map_file, []
    if args[0] != "--ros-args":
        raise TopolocError(f"unknown argument {args[0]!r} (ROS 2's arguments follow --ros-args)")
    if map_file is not None and (":=" in map_file or any(a in _ROS2_VALUE_FLAGS for a in args[-1:])):
        for k, a in enumerate(args):  # back where it was: after the flag that lacks its value
            if a in _ROS2_VALUE_FLAGS and (k + 1 == len(args) or args[k + 1].startswith("-")):
                args.insert(k + 1, map_file)
                return None, args
    return map_file, args


_SETTINGS: dict[str, Any] = {"allow_extra_args": True, "ignore_unknown_options": True}
app.command("ros-node", cls=needs(), help=ROS1_HELP, context_settings=_SETTINGS)(handle_errors(node_command))
app.command("ros2-node", cls=needs(), help=ROS2_HELP, context_settings=_SETTINGS)(handle_errors(node_command))
