"""What crosses the ROS interface, without importing ROS: message payloads <-> numpy (images, camera_info, poses,
match clouds), the node's parameters and DDS/QoS facts. The node and the bag tools share it."""
