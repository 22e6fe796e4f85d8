"""ROS-free algorithms, one package per capability; nothing under here imports rclpy.

geometry (cameras, views, poses, frames), tracking (the feature tracker: front-end and back-end
actor), sampling (Patch-Grid seeds), raster (the differentiable rasterizer and its backends),
mapping (the Gaussian map, the mapper, the mapping session and checkpoints), merge (voxel merging),
maps (map records, PLY files, deltas and replicas), metrics (image metrics, ATE, scoring) and
runtime (CPU tuning, the command-worker base, atomic writes).
"""
