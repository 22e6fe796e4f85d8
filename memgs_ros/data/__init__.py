"""Package data: the ORB vocabulary (built by ``python tools/build_vocabulary.py``)."""
