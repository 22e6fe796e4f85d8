"""Test-only machinery that the nodes read, never part of the product's parameters: see
:mod:`memgs_ros.testing.faults`."""
