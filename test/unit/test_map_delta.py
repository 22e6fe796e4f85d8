"""The map-delta wire format and the replica that applies it."""
from __future__ import annotations

import numpy as np
import pytest

from memgs_ros.core.gaussians.gaussian_map import GaussianRecords
from memgs_ros.core.map_io.map_delta import (
    ApplyStatus,
    MapReplica,
    MessageKind,
    decode,
    encode,
    f_rest_columns,
    message_dtype,
)
from memgs_ros.errors import MessageError


def _records(ids, seed=0, sh_degree=3) -> GaussianRecords:
    rng = np.random.default_rng(seed)
    n = len(ids)
    f_rest = np.zeros((n, 45), np.float32)
    cols = f_rest_columns(sh_degree)
    f_rest[:, cols] = rng.normal(size=(n, len(cols)))
    return GaussianRecords.from_arrays(np.asarray(ids), rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                                       f_rest, rng.normal(size=n), rng.normal(size=(n, 3)),
                                       rng.normal(size=(n, 4)))


def _same(a: GaussianRecords, b: GaussianRecords) -> bool:
    return all(np.array_equal(getattr(a, f), getattr(b, f))
               for f in ("ids", "xyz", "f_dc", "f_rest", "opacity", "scale", "rot"))


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_exact(degree: int) -> None:
    up = _records([3, 7, 9], sh_degree=degree)
    rows = encode(MessageKind.DELTA, 5, 42, up, np.array([1, 2]), degree)
    assert rows.dtype == message_dtype(degree)
    msg = decode(rows)
    assert (msg.kind, msg.seq, msg.total) == (MessageKind.DELTA, 5, 42)
    assert _same(msg.upserts, up)
    assert msg.removed_ids.tolist() == [1, 2]


def test_degree_zero_is_small() -> None:
    assert message_dtype(0).itemsize == 8 + 1 + 14 * 4
    assert message_dtype(3).itemsize == 8 + 1 + 59 * 4


def test_decode_rejects_malformed() -> None:
    rows = encode(MessageKind.DELTA, 1, 1, _records([1]), np.zeros(0), 3)
    with pytest.raises(MessageError, match="META"):
        decode(rows[1:])
    bad = rows.copy()
    bad["op"][1] = 9
    with pytest.raises(MessageError, match="unknown op"):
        decode(bad)
    nan = rows.copy()
    nan["x"][1] = np.nan
    with pytest.raises(MessageError, match="non-finite"):
        decode(nan)
    dropped = rows[[n for n in rows.dtype.names if n != "opacity"]]
    with pytest.raises(MessageError, match="opacity"):
        decode(np.array(dropped.tolist(), dtype=[(n, rows.dtype[n]) for n in dropped.dtype.names]))


def test_replica_follows_sequence_and_detects_gaps() -> None:
    rep = MapReplica()
    first = decode(encode(MessageKind.DELTA, 1, 3, _records([1, 2, 3]), np.zeros(0), 3))
    assert rep.apply(first) is ApplyStatus.APPLIED
    changed = _records([2, 4], seed=1)
    second = decode(encode(MessageKind.DELTA, 2, 3, changed, np.array([1]), 3))
    assert rep.apply(second) is ApplyStatus.APPLIED
    assert rep.records.ids.tolist() == [2, 3, 4]
    assert np.array_equal(rep.records.xyz[0], changed.xyz[0])
    assert rep.apply(second) is ApplyStatus.STALE
    fourth = decode(encode(MessageKind.DELTA, 4, 3, _records([5]), np.zeros(0), 3))
    assert rep.apply(fourth) is ApplyStatus.GAP
    assert rep.seq == 2 and rep.records.ids.tolist() == [2, 3, 4]


def test_late_replica_needs_snapshot_then_resyncs() -> None:
    rep = MapReplica()
    later = decode(encode(MessageKind.DELTA, 7, 2, _records([10]), np.zeros(0), 3))
    assert rep.apply(later) is ApplyStatus.NEEDS_SNAPSHOT
    snap_recs = _records([9, 4, 10], seed=3)
    snap = decode(encode(MessageKind.SNAPSHOT, 7, 3, snap_recs, np.zeros(0), 3))
    assert rep.apply(snap) is ApplyStatus.APPLIED
    assert rep.records.ids.tolist() == [4, 9, 10]
    nxt = decode(encode(MessageKind.DELTA, 8, 2, GaussianRecords.empty(), np.array([4]), 3))
    assert rep.apply(nxt) is ApplyStatus.APPLIED
    assert rep.records.ids.tolist() == [9, 10]


def test_count_mismatch_is_reported() -> None:
    rep = MapReplica()
    msg = decode(encode(MessageKind.DELTA, 1, 5, _records([1, 2]), np.zeros(0), 3))
    assert rep.apply(msg) is ApplyStatus.MISMATCH


def test_outbox_budgeted_deltas_keep_replica_in_step() -> None:
    from memgs_ros.core.map_io.map_delta import DeltaOutbox

    out, rep = DeltaOutbox(sh_degree=3), MapReplica()
    live = _records(range(10))
    first = out.next_delta(live, max_rows=4)
    assert rep.apply(decode(first)) is ApplyStatus.APPLIED and len(rep) == 4 and out.pending_rows == 6
    # 2 is at the receiver (needs a removal row); 7 never left the sender (nothing to remove).
    live = GaussianRecords.concat([live.select(~np.isin(live.ids, [2, 7])), _records([11], seed=5)])
    while (rows := out.next_delta(live, max_rows=3)) is not None:
        assert rep.apply(decode(rows)) is ApplyStatus.APPLIED
    assert rep.records.ids.tolist() == [0, 1, 3, 4, 5, 6, 8, 9, 11]
    assert out.pending_rows == 0 and out.next_delta(live) is None


def test_outbox_sends_only_changes_over_tolerance_then_flushes_exactly() -> None:
    from memgs_ros.core.map_io.map_delta import DeltaOutbox

    out, rep = DeltaOutbox(sh_degree=3, tolerance=1e-3), MapReplica()
    live = _records(range(5))
    rep.apply(decode(out.next_delta(live)))
    xyz = live.xyz.copy()
    xyz[1] += 1e-4  # below tolerance
    xyz[3] += 1e-2  # above
    live = GaussianRecords.from_arrays(live.ids, xyz, live.f_dc, live.f_rest, live.opacity, live.scale, live.rot)
    delta = decode(out.next_delta(live))
    assert delta.upserts.ids.tolist() == [3] and delta.removed_ids.size == 0
    rep.apply(delta)
    assert not np.array_equal(rep.records.xyz, live.xyz)
    assert rep.apply(decode(out.next_delta(live, tolerance=0.0))) is ApplyStatus.APPLIED
    assert _same(rep.records, live)


def test_outbox_snapshot_then_deltas() -> None:
    from memgs_ros.core.map_io.map_delta import DeltaOutbox

    out = DeltaOutbox(sh_degree=3)
    out.next_delta(_records([1, 2, 3]))
    full = _records([1, 2, 3, 4], seed=2)
    late = MapReplica()
    assert late.apply(decode(out.snapshot(full))) is ApplyStatus.APPLIED
    assert late.apply(decode(out.next_delta(full.select(np.array([1, 2, 3]))))) is ApplyStatus.APPLIED
    assert late.records.ids.tolist() == [2, 3, 4] and late.seq == 3
    in_step = MapReplica()
    in_step.apply(decode(encode(MessageKind.DELTA, 1, 3, _records([1, 2, 3]), np.zeros(0), 3)))
    # A delta overtaking the snapshot it follows is a gap, never silently applied.
    assert in_step.apply(decode(encode(MessageKind.DELTA, 3, 3, _records([9]), np.zeros(0), 3))) is ApplyStatus.GAP


def test_a_snapshot_of_the_map_the_last_delta_made_keeps_its_seq() -> None:
    """After the final flush the snapshot is the same map: a receiver that has the flush is done
    (the snapshot is no news), one that lost it takes the snapshot; a snapshot after any change,
    or after a delta that held rows back, takes a new seq."""
    from memgs_ros.core.map_io.map_delta import DeltaOutbox

    out, has, lost = DeltaOutbox(sh_degree=3), MapReplica(), MapReplica()
    first = decode(out.next_delta(_records([1, 2, 3], seed=1)))
    assert has.apply(first) is ApplyStatus.APPLIED and lost.apply(first) is ApplyStatus.APPLIED
    final = _records([1, 2, 4], seed=2)
    flush = decode(out.next_delta(final, tolerance=0.0))
    assert flush.seq == 2 and has.apply(flush) is ApplyStatus.APPLIED  # ``lost`` never gets it
    snap = decode(out.snapshot(final))
    assert snap.seq == 2
    assert has.apply(snap) is ApplyStatus.APPLIED and has.seq == 2 and _same(has.records, final)
    assert lost.apply(snap) is ApplyStatus.APPLIED and lost.seq == 2 and _same(lost.records, final)
    changed = _records([1, 2, 4], seed=3)
    assert decode(out.snapshot(changed)).seq == 3  # folds in a change no delta carried
    out.next_delta(_records([1, 2, 4, 5, 6], seed=3), max_rows=1)  # rows held back
    assert out.pending_rows > 0 and decode(out.snapshot(_records([1, 2, 4, 5, 6], seed=3))).seq == 5


def test_restarted_sender_new_epoch_resyncs_from_its_snapshot() -> None:
    from memgs_ros.core.map_io.map_delta import DeltaOutbox

    first = DeltaOutbox(sh_degree=3, epoch=7)
    rep = MapReplica()
    for ids in ([1, 2], [1, 2, 3], [2, 3, 4]):
        assert rep.apply(decode(first.next_delta(_records(ids, seed=len(ids))))) is ApplyStatus.APPLIED
    assert rep.epoch == 7 and rep.seq == 3
    # The sender restarts from an older state with a new epoch and numbers from 1 again.
    second = DeltaOutbox(sh_degree=3, epoch=(1 << 32) - 2)
    restored = _records([1, 2, 3, 10], seed=5)
    d = decode(second.next_delta(restored))
    assert d.epoch == (1 << 32) - 2 and d.seq == 1
    assert rep.apply(d) is ApplyStatus.NEW_EPOCH and rep.seq == 3  # untouched until the snapshot
    snap = decode(second.snapshot(restored))
    assert snap.seq == 1 and rep.apply(snap) is ApplyStatus.APPLIED  # the map delta 1 made
    assert rep.epoch == second.epoch and _same(rep.records, restored)
    assert rep.apply(decode(second.next_delta(restored.select(np.array([0, 3]))))) is ApplyStatus.APPLIED
    assert rep.records.ids.tolist() == [1, 10]
    # A snapshot of the old epoch arriving late is a new epoch too, and is taken as authoritative.
    old = decode(first.snapshot(_records([5])))
    assert rep.apply(old) is ApplyStatus.APPLIED and rep.epoch == 7
    with pytest.raises(ValueError, match="epoch"):
        encode(MessageKind.DELTA, 1, 0, _records([]), np.zeros(0), 3, epoch=1 << 32)
    rows = encode(MessageKind.DELTA, 1, 0, _records([]), np.zeros(0), 3, epoch=3)
    rows["x"][0] = 0.5
    with pytest.raises(MessageError, match="epoch"):
        decode(rows)


# ---------------------------------------------------------------- property-based
from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from hypothesis.extra import numpy as hnp  # noqa: E402

_DTYPE = message_dtype(0)


@settings(max_examples=150, deadline=None)
@given(hnp.arrays(_DTYPE, st.integers(0, 6)), st.sets(st.sampled_from(_DTYPE.names), max_size=3))
def test_decode_never_crashes_on_arbitrary_rows(rows: np.ndarray, drop: set[str]) -> None:
    """Any table of rows, with any fields missing, decodes or raises MessageError: nothing else."""
    kept = [n for n in _DTYPE.names if n not in drop]
    table = np.zeros(rows.shape, dtype=[(n, _DTYPE[n]) for n in kept])
    for n in kept:
        table[n] = rows[n]
    try:
        msg = decode(table)
    except MessageError:
        return
    assert np.all(np.isfinite(msg.upserts.xyz)) and len(msg.upserts) + msg.removed_ids.size == len(rows) - 1


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 2**40), unique=True, max_size=20), st.integers(1, 2**31), st.integers(0, 3))
def test_encode_decode_round_trip_property(ids: list[int], seq: int, degree: int) -> None:
    up = _records(ids, sh_degree=degree)
    msg = decode(encode(MessageKind.DELTA, seq, len(ids), up, np.zeros(0), degree))
    assert msg.seq == seq and _same(msg.upserts, up)
