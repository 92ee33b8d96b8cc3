"""``python -m topoloc.ros``: moved to ``python -m topoloc ros-node`` (or ``topoloc ros-node``); says so in one line.

The ROS package is run by the command line, never the reverse (issue #49: this entry imported the
command line from below it).  Nothing here imports :mod:`topoloc.cli`.
"""

from __future__ import annotations

import shlex
import sys


def main() -> int:
    """One line naming the command to run instead, with this process's arguments; exit status 2."""
    args = " ".join(shlex.quote(a) for a in sys.argv[1:])
    print("topoloc: error: the node runs as `python -m topoloc ros-node` (or `topoloc ros-node`), not "
          f"`python -m topoloc.ros`: python -m topoloc ros-node {args}".rstrip(), file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
