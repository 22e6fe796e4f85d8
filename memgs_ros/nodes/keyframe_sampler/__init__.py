"""The keyframe sampler node: Patch-Grid keyframe selection."""
