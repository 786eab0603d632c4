"""Bouc-Wen hysteresis models and piezo plant dynamics (thesis ch. 8, 9.1.1-9.1.2, 10.2, 11.2). No rclpy."""
