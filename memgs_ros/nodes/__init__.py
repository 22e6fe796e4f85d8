"""Thin rclpy nodes: messages and parameters in, core calls, messages out."""
