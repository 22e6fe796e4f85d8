"""What tests and benchmarks put beside a graph, never inside a node: :mod:`memgs_ros.testing.delta_relay`
(a lossy link for the map deltas)."""
