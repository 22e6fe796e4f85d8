"""Loop closing: place recognition over the vocabulary, loop verification and the pose graph."""
