"""ros2 launch topoloc_ros localize.launch.py map:=/path/route.tlm image:=/camera/image_raw [queue:=1] [sequence:=-1]

topoloc's ROS 2 node beside a camera driver: the map, the camera's image topic (remapped onto the node's
`image`), and the settings most often changed; every other parameter of the node (docs/ros.md) can be added to
the dictionary below. Include it in the driver's launch file, or run it on its own.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    args = [
        DeclareLaunchArgument("map", description="the map file (topoloc map build)"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw", description="the camera's image topic"),
        DeclareLaunchArgument("queue", default_value="1", description="frames that may wait; older ones skipped"),
        DeclareLaunchArgument("sequence", default_value="-1",
                              description="frames matched with each one; -1: as the map was calibrated"),
        DeclareLaunchArgument("namespace", default_value="", description="the node's namespace"),
    ]
    node = Node(
        package="topoloc_ros",
        executable="topoloc_node",
        name="topoloc",
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        parameters=[{
            "map": LaunchConfiguration("map"),
            "queue": ParameterValue(LaunchConfiguration("queue"), value_type=int),
            "sequence": ParameterValue(LaunchConfiguration("sequence"), value_type=int),
        }],
        remappings=[("image", LaunchConfiguration("image"))],
    )
    return LaunchDescription([*args, node])
