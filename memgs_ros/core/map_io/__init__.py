"""The map in and out of a process (core/mapping/ trains it): PLY files and map bundles, the deltas
and replicas that carry a map from the mapper to a merger, its renders there, the services' answers."""
