"""bevo_node with its parameters, optionally a bag replay and RViz.

    ros2 launch bevo_ros bevo.launch.py                                  # live sensors
    ros2 launch bevo_ros bevo.launch.py bag:=bags/kitti06               # replay (use_sim_time on)
    ros2 launch bevo_ros bevo.launch.py namespace:=car1 params_file:=/path/car.yaml rviz:=true

Arguments:
    params_file   bevo_node parameters (default: the installed share/bevo_ros/params/kitti.yaml);
                  a relative learned_params_file in it resolves beside it
    use_sim_time  follow /clock (default: true when bag is given, else false)
    namespace     push the node (and its relative topics) into this namespace
    bag           a rosbag2 to replay with the project's player (play_bag = `bevo play`, /clock, recorded QoS);
                  the node then also loads params/replay.yaml (reliable inputs: no frame lost)
    rate          replay speed factor (default 1.0)
    rviz          start RViz with share/bevo_ros/rviz/bevo.rviz (default false), in the namespace
    localizer     also start bevo_localizer (BEVO+, map -> odom) on map_file (default false)
    map_file      the localizer's map YAML (nav2 map_server convention)
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, ExecuteProcess
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import LaunchConfiguration, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import ExecutableInPackage

PACKAGE = "bevo_ros"
# The topics rviz/bevo.rviz shows (absolute there, as RViz stores them): remapped to relative names so that
# RViz, pushed into the launch's namespace, shows that namespace's node.
# "2D Pose Estimate" (/initialpose) likewise reaches the namespace's bevo_localizer.
RVIZ_TOPICS = ("/bevo/odometry", "/bevo/path", "/bevo/bev_image", "/ground_truth/odometry", "/camera/image_rect",
               "/initialpose")


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    params_file = LaunchConfiguration("params_file")
    use_sim_time = LaunchConfiguration("use_sim_time")
    namespace = LaunchConfiguration("namespace")
    bag = LaunchConfiguration("bag")
    rate = LaunchConfiguration("rate")
    rviz = LaunchConfiguration("rviz")
    localizer = LaunchConfiguration("localizer")
    map_file = LaunchConfiguration("map_file")
    has_bag = PythonExpression(["'", bag, "' != ''"])

    def bevo_node(params: list, condition) -> Node:
        return Node(package=PACKAGE, executable="bevo_node", name="bevo_node", namespace=namespace, output="screen",
                    emulate_tty=True, condition=condition,
                    parameters=[*params, {"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}])

    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "params", "kitti.yaml"),
                              description="bevo_node parameters file"),
        # bag before use_sim_time: an argument's default is evaluated where it is declared, and
        # use_sim_time's reads bag (declared after it, every launch without bag:= failed)
        DeclareLaunchArgument("bag", default_value="", description="rosbag2 to replay (empty: live sensors)"),
        DeclareLaunchArgument("use_sim_time", default_value=PythonExpression(["'true' if '", bag, "' else 'false'"]),
                              description="follow /clock (true by default when a bag is replayed)"),
        DeclareLaunchArgument("namespace", default_value="", description="namespace of the node and its topics"),
        DeclareLaunchArgument("rate", default_value="1.0", description="bag replay speed factor"),
        DeclareLaunchArgument("rviz", default_value="false", description="start RViz"),
        DeclareLaunchArgument("localizer", default_value="false",
                              description="start bevo_localizer (BEVO+: map -> odom from an aerial map)"),
        DeclareLaunchArgument("map_file", default_value="", description="bevo_localizer's map YAML"),
        # live sensors: the params file as it is (best-effort sensor inputs); a bag replay:
        # params/replay.yaml on top (reliable inputs: no frame lost, the same result as `bevo run`)
        bevo_node([params_file], UnlessCondition(has_bag)),
        bevo_node([params_file, os.path.join(share, "params", "replay.yaml")], IfCondition(has_bag)),
        Node(
            package=PACKAGE,
            executable="bevo_localizer",
            name="bevo_localizer",
            namespace=namespace,
            output="screen",
            emulate_tty=True,
            parameters=[os.path.join(share, "params", "bevo_localizer.yaml"),
                        {"map_file": ParameterValue(map_file, value_type=str),
                         "use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
            condition=IfCondition(localizer),
        ),
        ExecuteProcess(
            cmd=[ExecutableInPackage(executable="play_bag", package=PACKAGE), bag, "--rate", rate,
                 "--namespace", namespace, "--wait-for-subscribers", "10",
                 "--wait-params", params_file],  # the node's inputs in its parameters, the speed among them
            output="screen",
            condition=IfCondition(has_bag),
        ),
        Node(
            package="rviz2",
            executable="rviz2",
            name="rviz2",
            namespace=namespace,
            arguments=["-d", os.path.join(share, "rviz", "bevo.rviz")],
            remappings=[(topic, topic.lstrip("/")) for topic in RVIZ_TOPICS],
            parameters=[{"use_sim_time": ParameterValue(use_sim_time, value_type=bool)}],
            condition=IfCondition(rviz),
        ),
    ])
