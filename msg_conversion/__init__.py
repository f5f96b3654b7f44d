"""Conversions between ROS messages (rclpy or rosbags classes) and numpy / shape_detector types."""
