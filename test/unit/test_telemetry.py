"""The typed stats records: a key a record does not name is refused, the values read with their
types, and the run summary's figures come from fields (a renamed counter fails here, not as 0)."""
from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import pytest

from memgs_ros.core.mapper_service.session_records import SessionStatus
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
    from memgs_ros.core.mapper_service.session_records import SessionCounts
    from memgs_ros.core.runtime.telemetry_fields import MapperFields
    assert issubclass(SessionCounts, MapperFields)  # the session's counters are written by attribute
    counts = SessionCounts()
    counts.keyframes += 2
    for key in counts.with_map(1, 2):
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


def test_the_generated_fields_are_the_records_own() -> None:
    """telemetry_fields.py is what stat_fields writes from the records now (regenerate after an edit)."""
    from memgs_ros.core.runtime import stat_fields

    assert stat_fields.main([]) == 0, "python -m memgs_ros.core.runtime.stat_fields --write"
    from memgs_ros.core.runtime.telemetry_fields import MapperFields, TrackerFields
    assert TrackerFields.frames_in.key == "frames_in" and TrackerFields.problem_counts.key == "problem"
    assert MapperFields.loss.default is None and TrackerFields.skipped.key == "skipped"


_STRING_WRITE = re.compile(r"""(?:counters|gauges|computed)\[|post_(?:count|counter|gauge)\(|(?:counters|gauges)\.update\(""")


def test_no_stats_key_is_written_as_a_string() -> None:
    """Nodes write their stats by attribute (``stats.frames_in += 1``), never by a string key
    that only fails when the line runs (the bag reader's per-topic message counters aside)."""
    root = Path(__file__).resolve().parents[2] / "memgs_ros"
    found = [f"{p.relative_to(root)}:{n}" for p in sorted(root.rglob("*.py")) if p.name != "bag_reader.py"
             for n, line in enumerate(p.read_text().splitlines(), 1) if _STRING_WRITE.search(line)]
    assert found == []


def test_mypy_catches_a_misspelt_or_mistyped_stats_field(tmp_path: Path) -> None:
    """The point of the generated fields: a write to a field the record does not name, or of the
    wrong type, fails type checking (test_lint runs mypy over every node)."""
    import subprocess
    import sys

    root = Path(__file__).resolve().parents[2]
    probe = tmp_path / "probe.py"
    probe.write_text("from memgs_ros.core.runtime.telemetry_fields import TrackerFields\n\n\n"
                     "def write(stats: TrackerFields) -> None:\n"
                     "    stats.frames_in += 1\n    stats.skipped['busy'] += 1\n"
                     "    stats.frames_inn += 1\n    stats.tracking_state = 3\n")
    r = subprocess.run([sys.executable, "-m", "mypy", "--no-incremental", "--follow-imports=silent", str(probe)],
                       cwd=root, capture_output=True, text=True, timeout=300)
    assert r.returncode == 1, r.stdout + r.stderr
    assert '"TrackerFields" has no attribute "frames_inn"' in r.stdout
    assert 'probe.py:8: error: Incompatible types in assignment' in r.stdout
    assert "probe.py:5" not in r.stdout and "probe.py:6" not in r.stdout


def test_the_tracking_state_counts_resets_and_says_when_tracking_is_lost_or_back() -> None:
    from memgs_ros.core.runtime.stat_fields import StatValues
    from memgs_ros.core.runtime.telemetry_fields import TrackerFields
    from memgs_ros.core.tracking.telemetry import state_stats

    class Stats(TrackerFields, StatValues):
        pass

    stats = Stats()
    says = [state_stats(stats, name, seg) for name, seg in
            [("OK", 0), ("OK", 0), ("RECENTLY_LOST", 0), ("LOST", 0), ("LOST", 0), ("OK", 0), ("OK", 1)]]
    assert says == [False, False, False, True, False, True, False]  # lost, and back: at once
    assert stats.resets == 2  # relocalised (LOST -> OK) and a new segment (0 -> 1)
    assert (stats.tracking_state, stats.segment) == ("OK", 1)
    assert stats.values["state.OK"] == 4 and stats.values["state.LOST"] == 2
