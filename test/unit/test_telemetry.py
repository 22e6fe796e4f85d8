"""The typed stats records: a key a record does not name is refused, the values read with their
types, and the run summary's figures come from fields (a renamed counter fails here, not as 0)."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from memgs_ros.core.mapping.session_records import SessionStatus
from memgs_ros.core.runtime.telemetry import (
    TELEMETRY,
    MapperTelemetry,
    PlayerTelemetry,
    StatsError,
    TrackerTelemetry,
    check_key,
    parse_stats,
)


def test_values_read_with_their_types_and_families_gather_by_prefix() -> None:
    t = parse_stats(TrackerTelemetry, {"frames_in": "12", "frame_cpu_ms_median": "3.5", "state.LOST": "2",
                                       "skipped.busy": "1.0", "problem.bad_image": "4"})
    assert t.frames_in == 12 and isinstance(t.frames_in, int)
    assert t.frame_cpu_ms_median == 3.5
    assert t.state == {"LOST": 2} and t.skipped == {"busy": 1} and t.problem == {"bad_image": 4}
    assert t.keyframes == 0  # not reported yet: the record's default


def test_a_key_no_record_field_names_is_an_error_not_a_zero() -> None:
    with pytest.raises(StatsError, match="has no stats key 'frames'"):
        parse_stats(TrackerTelemetry, {"frames": "12"})
    with pytest.raises(StatsError, match="has no stats key 'skipped'"):
        check_key(PlayerTelemetry, "skipped")  # a family takes members only
    with pytest.raises(StatsError, match="is not a int"):
        parse_stats(PlayerTelemetry, {"frames_published": "many"})


def test_optional_figures_stay_none_until_reported() -> None:
    m = parse_stats(MapperTelemetry, {"iteration": "5"})
    assert m.cuda_max_allocated is None and m.keyframe_latency_ms_median is None
    m = parse_stats(MapperTelemetry, {"cuda_max_allocated": "1048576", "cuda_peak_mb.backward": "3.5"})
    assert m.cuda_max_allocated == 2**20 and m.cuda_peak_mb == {"backward": 3.5}


def test_the_mapping_sessions_gauges_and_counters_are_mapper_fields() -> None:
    """The mapper reports its session's status as it is: each key must be a field of its record."""
    status = dataclasses.replace(SessionStatus(), iteration=3, loss=0.1, cuda_max_allocated=5,
                                 cuda_peak_by_work={"backward": 2**20})
    for key in status.gauges():
        check_key(MapperTelemetry, key)
    import inspect
    import re

    from memgs_ros.core.mapping import session
    counters = set(re.findall(r'(?:_counters|c)\["(\w+)"\]', inspect.getsource(session)))
    assert counters >= {"keyframes", "train_commands", "merged_added"}
    for key in counters:
        check_key(MapperTelemetry, key)


def test_every_node_the_runner_watches_has_a_record() -> None:
    from memgs_ros.orchestration.graph_watch import STATS_NODES
    assert set(STATS_NODES) <= set(TELEMETRY)


def test_the_stats_keys_read_from_a_saved_timeline_are_record_fields() -> None:
    """``memgs view`` and the Rerun plots read stats_timeline.jsonl by key: each key must be one a
    node reports."""
    from memgs_ros.orchestration.saved_run import STATS_KEYS
    from memgs_ros.viz.rerun_log import PLOTTED_STATS

    for key in (*STATS_KEYS, *PLOTTED_STATS):
        assert any(_names(r, key) for r in TELEMETRY.values()), key


def _names(record: type, key: str) -> bool:
    try:
        check_key(record, key)
    except StatsError:
        return False
    return True


# Which record each file's stats writes go to (the node whose NodeStats it is handed).
_WRITERS = {
    "nodes/tracker/node.py": "tracker", "nodes/tracker/outputs.py": "tracker", "nodes/tracker/inputs.py": "tracker",
    "nodes/keyframe_sampler/node.py": "keyframe_sampler",
    "nodes/mapper/node.py": "mapper", "nodes/mapper/stats.py": "mapper", "core/mapping/checkpoint_saver.py": "mapper",
    "nodes/merger/node.py": "merger", "nodes/merger/outputs.py": "merger", "ros/map_bundles.py": "merger",
    "nodes/tracker/map_part.py": "tracker", "nodes/mapper/map_part.py": "mapper",
    "nodes/bag_player/node.py": "player", "nodes/recorder/node.py": "recorder",
    "nodes/rerun_bridge/node.py": "rerun_bridge", "viz/live_view.py": "rerun_bridge",
}
_WRITE = re.compile(r"""(?:counters|gauges|computed|\b(?<!\.)g)\["([\w.]+)"\]|post_(?:count|counter|gauge)\("([\w.]+)"|"""
                    r"""gauges\.update\(((?:\w+=[^,)]+,?\s*)+)\)""")


def test_every_stats_key_a_node_writes_is_a_field_of_its_record() -> None:
    """Read from the source: a key written by a path no test runs (a warm-up's gauge, a rare
    counter) is checked here too, and a file that writes stats must be listed above."""
    root = Path(__file__).resolve().parents[2] / "memgs_ros"
    writers = {str(p.relative_to(root)) for p in root.rglob("*.py") if _WRITE.search(p.read_text())}
    # the stats class; the session's own Counter; a tensor ``g["..."]`` of gradients
    writers -= {"ros/diagnostics.py", "core/mapping/session.py", "core/gaussians/gaussian_map.py"}
    assert writers <= set(_WRITERS), f"stats writers not mapped to a node: {sorted(writers - set(_WRITERS))}"
    missing = []
    for rel, node in _WRITERS.items():
        for m in _WRITE.finditer((root / rel).read_text()):
            keys = [m.group(1) or m.group(2)] if not m.group(3) else re.findall(r"(\w+)=", m.group(3))
            for key in keys:
                if not _names(TELEMETRY[node], key):
                    missing.append(f"{rel}: {key!r} is not a field of {TELEMETRY[node].__name__}")
    assert missing == []
