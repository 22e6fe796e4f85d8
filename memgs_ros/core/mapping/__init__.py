"""The Gaussian mapper: the map and its Adam state (``gaussians``), training keyframes and view
selection, losses and exposure compensation, the densify/prune/budget strategies, the mapper
itself, the mapping session that owns it (an actor) and its checkpoints."""
