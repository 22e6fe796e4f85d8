"""The layout's size bounds (issue 37): thin nodes over core services, short functions, no giant
class. ``python benchmarks/layout_figures.py`` prints the figures these bound."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from layout_figures import figures, layering  # noqa: E402 - the benchmarks folder is not a package

# ros2/demos nodes are 50-100 lines; ours translate messages and parameters over core services.
# Each bound sits about 10 % above the size measured when it was set (issue 49: TrackerNode 180,
# other nodes 150, largest class 350; MapperNode 235 on 12-03), so a small change does not trip it
# and growth past that does.
NODE_BOUNDS = {"TrackerNode": 198, "MapperNode": 260}
OTHER_NODE_BOUND = 165
FUNCTION_BOUND = 80
CLASS_BOUND = 385
# A node's package (issue 49 asks <= 700 lines of the benchmark's figure): 10 % above the largest on 12-04
# (the tracker, 693; it had grown to 730 unnoticed before this bound).
NODE_FOLDER_BOUND = 765


def test_nodes_are_thin() -> None:
    f = figures()
    nodes = f["nodes"]
    assert {"TrackerNode", "MapperNode", "MergerNode", "BagPlayer", "RerunBridgeNode"} <= set(nodes)
    fat = {n: lines for n, lines in nodes.items() if lines > NODE_BOUNDS.get(n, OTHER_NODE_BOUND)}
    assert fat == {}, "node classes over their bound (move the logic into a core service)"


def test_no_function_is_over_80_lines_and_no_class_over_the_bound() -> None:
    f = figures(longest=FUNCTION_BOUND)
    assert f["functions_over"] == []
    assert f["largest_classes"][0][0] <= CLASS_BOUND, f["largest_classes"][0]


def test_no_node_package_is_over_the_bound() -> None:
    folders = layering()["node_package_lines"]
    assert "tracker" in folders and "mapper" in folders  # type: ignore[operator]
    fat = {n: lines for n, lines in folders.items() if lines > NODE_FOLDER_BOUND}  # type: ignore[union-attr]
    assert fat == {}, "node packages over their bound (move what needs no ROS into core, what nodes share into ros/)"
