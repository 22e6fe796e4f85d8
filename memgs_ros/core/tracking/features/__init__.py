"""Features: ORB extraction (OpenCV's FAST spread over a grid, a numba descriptor kernel), the
frame's keypoints and descriptors, and the place-recognition vocabulary."""
