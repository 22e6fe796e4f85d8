"""The merger node: the map replica, rendered views, PLY and map bundles."""
