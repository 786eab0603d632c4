"""rosbag2/MCAP writing, reading, reindexing and export helpers. No rclpy."""
