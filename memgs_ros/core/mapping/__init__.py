"""The Gaussian mapper: training keyframes and view selection, losses and exposure compensation,
the densify/prune/budget strategies, the mapper itself, the mapping session that owns it (an actor)
and its checkpoints. The trainable map itself is ``core/gaussians``."""
