"""The layout's size bounds (issue 37): thin nodes over core services, short functions, no giant
class. ``python benchmarks/layout_figures.py`` prints the figures these bound."""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from layout_figures import figures  # noqa: E402 - the benchmarks folder is not a package

# ros2/demos nodes are 50-100 lines; ours translate messages and parameters over core services.
# Each bound sits about 10 % above the size measured when it was set (issue 49: TrackerNode 180,
# other nodes 150, largest class 350; MapperNode 235 on 12-03), so a small change does not trip it
# and growth past that does.
NODE_BOUNDS = {"TrackerNode": 198, "MapperNode": 260}
OTHER_NODE_BOUND = 165
FUNCTION_BOUND = 80
CLASS_BOUND = 385


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
