"""The front-end: per-frame tracking (FeatureTracker and its RGB-D and monocular forms), matching
by projection on the local map, pose optimisation, relocalisation, and the link that applies the
back-end's corrections to the sparse map."""
