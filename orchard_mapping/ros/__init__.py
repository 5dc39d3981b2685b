"""The ROS 2 side of orchard_mapping: message conversions (and, later, the nodes). Imports rclpy's message
packages; the algorithm core (`orchard_mapping.core`) never imports this."""
