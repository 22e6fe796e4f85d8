"""The back-end: the actor (TrackingBackend) that runs local and global bundle adjustment off the
frame path, and the solvers it calls."""
