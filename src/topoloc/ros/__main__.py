"""``python -m topoloc.ros MAP [options] [NAME:=VALUE ...]``: ``topoloc ros-node`` (see ``docs/ros.md``)."""

from __future__ import annotations

import sys

from topoloc.cli.main import app


def main() -> None:
    """Run ``topoloc ros-node`` with this process's arguments."""
    app(args=["ros-node", *sys.argv[1:]], prog_name="python -m topoloc.ros")


if __name__ == "__main__":
    main()
