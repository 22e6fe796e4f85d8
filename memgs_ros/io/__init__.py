"""Datasets and bags: TUM folders, the synthetic scene generator, rosbags read/write (no rclpy)."""
