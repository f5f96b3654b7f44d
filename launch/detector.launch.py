"""Launch shape_detector's detector_node with RealSense (realsense2_camera 4.x) remappings.

    ros2 launch shape_detector detector.launch.py
    ros2 launch shape_detector detector.launch.py params_file:=/path/to.yaml use_sim_time:=true \
        image:=/camera/color/image_raw depth:=/camera/aligned_depth_to_color/image_raw \
        camera_info:=/camera/color/camera_info

The RealSense driver must publish depth aligned to colour (``align_depth.enable:=true``).
With ``up_source:=imu`` (in the params file) remap ``imu`` to the camera's IMU topic
(``enable_gyro/enable_accel``, ``unite_imu_method``) and set ``imu_to_camera``.
The scene map (``~/scene``, ``~/map``, ``~/surfaces``, ``~/get_plan``) takes the camera pose
from ``/tf`` (where tf2_ros is installed), the ``odom`` or the ``pose`` topic (remap them), as
``pose_source`` and ``world_frame`` in the params file say.
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    """The detector node with its parameters file and the usual camera topic remaps."""
    args = [
        DeclareLaunchArgument(
            "params_file",
            default_value=PathJoinSubstitution([FindPackageShare("shape_detector"), "config", "detector.yaml"]),
            description="detector_node parameters (YAML with ros__parameters)",
        ),
        DeclareLaunchArgument("use_sim_time", default_value="false", description="use /clock (bag playback)"),
        DeclareLaunchArgument("namespace", default_value="", description="node namespace"),
        DeclareLaunchArgument("node_name", default_value="shape_detector", description="node name"),
        DeclareLaunchArgument("image", default_value="/camera/camera/color/image_raw", description="colour image topic"),
        DeclareLaunchArgument(
            "depth",
            default_value="/camera/camera/aligned_depth_to_color/image_raw",
            description="depth image topic, registered to the colour camera",
        ),
        DeclareLaunchArgument(
            "camera_info", default_value="/camera/camera/color/camera_info", description="colour camera_info topic"
        ),
        DeclareLaunchArgument("imu", default_value="/camera/camera/imu", description="IMU topic (up_source=imu)"),
        DeclareLaunchArgument(
            "detections2d", default_value="detections2d", description="Detection2DArray topic (proposal_source=external)"
        ),
        DeclareLaunchArgument("odom", default_value="odom", description="nav_msgs/Odometry camera pose topic "
                              "(pose_source odom or auto)"),
        DeclareLaunchArgument("pose", default_value="pose", description="geometry_msgs/PoseStamped camera pose topic "
                              "(pose_source pose or auto)"),
        DeclareLaunchArgument("log_level", default_value="info", description="ROS log level"),
    ]
    node = Node(
        package="shape_detector",
        executable="detector_node",
        name=LaunchConfiguration("node_name"),
        namespace=LaunchConfiguration("namespace"),
        output="screen",
        emulate_tty=True,
        parameters=[
            LaunchConfiguration("params_file"),
            {"use_sim_time": ParameterValue(LaunchConfiguration("use_sim_time"), value_type=bool)},
        ],
        remappings=[
            ("image", LaunchConfiguration("image")),
            ("depth", LaunchConfiguration("depth")),
            ("camera_info", LaunchConfiguration("camera_info")),
            ("imu", LaunchConfiguration("imu")),
            ("detections2d", LaunchConfiguration("detections2d")),
            ("odom", LaunchConfiguration("odom")),
            ("pose", LaunchConfiguration("pose")),
        ],
        arguments=["--ros-args", "--log-level", LaunchConfiguration("log_level")],
    )
    return LaunchDescription(args + [node])
