"""Time-varying PID control laws, Theorem 4 gain design and sampled-loop checks (thesis ch. 11). No rclpy."""
