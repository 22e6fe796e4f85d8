"""Geometry of cameras and poses: pinhole cameras with distortion and their undistorted views,
poses and rotations (SE(3), quaternions), and the RGB-D ``Frame`` every source yields."""
