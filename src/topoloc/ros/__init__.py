"""topoloc on a running ROS 1 graph: a node that localises an image topic against a saved map.

``topoloc ros-node MAP`` (or ``python -m topoloc ros-node MAP``) subscribes to an
image topic, localises the newest frame through :meth:`topoloc.maps.Map.localizer`
and publishes the answers (:mod:`topoloc.ros.node`; topics, messages and
parameters in ``docs/ros.md``).

ROS 1 is not on PyPI: ``rospy`` and the message packages come from the
system's packages (Debian 12: ``apt-get install ros-base python3-rospy
python3-sensor-msgs python3-geometry-msgs python3-diagnostic-msgs python3-std-srvs``),
into the system Python's ``dist-packages``.  :func:`import_rospy` lets the
Python that runs topoloc (a virtual environment, with its own NumPy, OpenCV
and faiss) import them without letting either side shadow the other: the
system folder is appended to the *end* of ``sys.path``, after every folder of
this environment, and only after NumPy is imported, so ``numpy`` (and every
other package installed here) is this environment's, and only what this
environment lacks (``rospy``, ``genpy``, the messages) comes from the system.
The ROS packages used are pure Python, so they run on any NumPy.
"""

from __future__ import annotations

import os
import sys
from types import ModuleType

from topoloc.errors import TopolocError

#: Where Debian (and Ubuntu) install the Python modules of their ROS 1 packages.
SYSTEM_DIST_PACKAGES = "/usr/lib/python3/dist-packages"

#: The system packages the node needs, as Debian 12 names them.
DEBIAN_PACKAGES = ("ros-base", "python3-rospy", "python3-sensor-msgs", "python3-geometry-msgs",
                   "python3-diagnostic-msgs", "python3-std-srvs")

MISSING_ROS = ("the ROS node needs ROS 1's rospy and messages, which are not on PyPI: "
               f"apt-get install {' '.join(DEBIAN_PACKAGES)} (Debian 12), or set TOPOLOC_ROS_PYTHONPATH to "
               "the folder that holds rospy")


def ros_paths() -> list[str]:
    """Folders searched for ``rospy`` after this environment's: ``$TOPOLOC_ROS_PYTHONPATH``, then Debian's."""
    extra = [p for p in os.environ.get("TOPOLOC_ROS_PYTHONPATH", "").split(os.pathsep) if p]
    return [*extra, SYSTEM_DIST_PACKAGES]


def import_rospy() -> ModuleType:
    """``rospy``, from this environment if it has it, else from the system's ROS packages (see the module).

    Raises
    ------
    TopolocError
        One line naming the packages to install when ``rospy`` or a message package is found nowhere.
    """
    import numpy  # noqa: F401  (this environment's NumPy is imported first: no later path can replace it)

    try:
        import rospy
    except ImportError:
        for path in ros_paths():
            if os.path.isdir(path) and path not in sys.path:
                sys.path.append(path)  # last: every package of this environment comes first
        try:
            import rospy
        except ImportError:
            raise TopolocError(MISSING_ROS) from None
    try:
        import diagnostic_msgs.msg  # noqa: F401
        import geometry_msgs.msg  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
    except ImportError as exc:
        raise TopolocError(f"{MISSING_ROS} ({exc.name} is missing)") from None
    return rospy


__all__ = ["DEBIAN_PACKAGES", "MISSING_ROS", "SYSTEM_DIST_PACKAGES", "import_rospy", "ros_paths"]
