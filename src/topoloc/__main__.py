"""``python -m topoloc COMMAND ...``: the command line (:mod:`topoloc.cli`), as the ``topoloc`` script runs it.

The one entry point above every layer: ``python -m topoloc ros-node MAP ...`` is how a ROS
launch file or ``rosrun`` starts the node (``topoloc_ros/scripts/topoloc_node``), so that the ROS
package (:mod:`topoloc.ros`) never imports the command line that runs it (issue #49).
"""

from __future__ import annotations

from topoloc.cli.main import app


def main() -> None:
    """Run the command line with this process's arguments, named ``python -m topoloc`` in its help."""
    app(prog_name="python -m topoloc")


if __name__ == "__main__":
    main()
