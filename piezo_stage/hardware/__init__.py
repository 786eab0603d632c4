"""Device wire protocols (PI GCS2, Thorlabs MDT69x, Micro-Epsilon optoNCDT) and their emulators. No rclpy."""
