"""Thin rclpy nodes: parameters, topics and timers around the pure core."""
