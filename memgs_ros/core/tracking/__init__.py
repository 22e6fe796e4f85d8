"""Front-end visual odometry (feature tracker for RGB-D and monocular cameras)."""
