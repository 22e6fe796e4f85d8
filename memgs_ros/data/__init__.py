"""Package data: the ORB vocabulary (built by ``python benchmarks/build_vocabulary.py``)."""
