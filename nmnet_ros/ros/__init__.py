"""The ROS 2 node (rclpy) and its console script."""
