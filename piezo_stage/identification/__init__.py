"""Analytic limit-cycle identification of the (modified) normalized Bouc-Wen model (thesis ch. 9-10). No rclpy."""
