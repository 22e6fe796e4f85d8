"""The mapper node: keyframe intake, map outputs, stats, its map part."""
