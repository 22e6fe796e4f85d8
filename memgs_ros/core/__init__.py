"""ROS-free algorithms: camera, geometry, Gaussian map, rasterizer, losses, merge,
sampling, tracking and metrics. Nothing under here imports rclpy."""
