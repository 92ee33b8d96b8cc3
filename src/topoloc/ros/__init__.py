"""topoloc on a running ROS graph: a node that localises an image topic against a saved map.

``topoloc ros-node MAP`` (or ``python -m topoloc ros-node MAP``; ROS 1, :mod:`topoloc.ros.node`) and ``topoloc ros2-node
MAP`` (ROS 2, :mod:`topoloc.ros.node2`) subscribe to an image topic, localise the
newest frame through :meth:`topoloc.maps.Map.localizer_for` and publish the
answers; what they share, with no ROS in it, is :mod:`topoloc.ros.core` (topics,
messages and parameters in ``docs/ros.md``).

ROS 2's ``rclpy`` and its messages are on PyPI as wheels (``pip install
'topoloc[ros2]'``: rclpy of ROS 2 Kilted with Fast DDS); :func:`import_rclpy`
imports them, or says in one line what is missing.

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


#: The extra that installs ROS 2's rclpy and the messages the ROS 2 node uses.
ROS2_EXTRA = "pip install 'topoloc[ros2]'"

MISSING_ROS2 = (f"the ROS 2 node needs rclpy and the messages sensor_msgs, std_msgs, geometry_msgs, diagnostic_msgs "
                f"and std_srvs: {ROS2_EXTRA} (ROS 2 wheels from PyPI), or source a ROS 2 installation")


def import_rclpy() -> ModuleType:
    """``rclpy``, with the message packages the ROS 2 node uses.

    Raises
    ------
    TopolocError
        One line naming what is missing (a package, or ROS 2's libraries where
        ``rclpy`` is installed but its process was started without them).
    """
    try:
        import rclpy
    except ImportError as exc:
        if exc.name == "rclpy":
            raise TopolocError(f"{MISSING_ROS2} ({exc.name} is missing)") from None
        # rclpy is there, its C libraries not found: the wheels' .pth hook (ros_wheels_bootstrapper) sets
        # LD_LIBRARY_PATH by starting the process again, unless a parent already set its guard variable.
        raise TopolocError(f"rclpy cannot load ROS 2's libraries ({exc}); start the process afresh from the "
                           "environment rclpy is installed in, without _ROS_WHEELS_BOOTSTRAP_COMPLETE set") from None
    try:
        import diagnostic_msgs.msg  # noqa: F401
        import geometry_msgs.msg  # noqa: F401
        import rcl_interfaces.msg  # noqa: F401
        import sensor_msgs.msg  # noqa: F401
        import std_msgs.msg  # noqa: F401
        import std_srvs.srv  # noqa: F401
    except ImportError as exc:
        raise TopolocError(f"{MISSING_ROS2} ({exc.name} is missing)") from None
    return rclpy


__all__ = ["DEBIAN_PACKAGES", "MISSING_ROS", "MISSING_ROS2", "ROS2_EXTRA", "SYSTEM_DIST_PACKAGES", "import_rclpy",
           "import_rospy", "ros_paths"]
