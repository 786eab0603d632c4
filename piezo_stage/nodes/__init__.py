"""Thin rclpy nodes: one per core module (parameters, topics, timers only)."""
