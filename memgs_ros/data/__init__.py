"""Package data: the ORB vocabulary (built by ``python -m memgs_ros.core.tracking.vocabulary``)."""
