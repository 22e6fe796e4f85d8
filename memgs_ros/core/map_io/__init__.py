"""A Gaussian map as data outside the trainer: host records (the 3DGS PLY fields), PLY files, and
the deltas and replicas that carry a map from the mapper to a merger."""
