"""The tracker node: camera input, the tracking front-end's outputs (poses, path, odometry, TF), its map part."""
