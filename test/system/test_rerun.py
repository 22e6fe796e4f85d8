"""The Rerun view: splat conversion against Rerun's own PLY loader, `memgs view`, the errors without
rerun-sdk, and `memgs run --rerun-save` end to end. Recordings are read back with Rerun's reader."""
from __future__ import annotations

import json
import os
import sys
from collections import defaultdict
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import cv2
import numpy as np
import pyarrow as pa
import pytest

rr = pytest.importorskip("rerun", reason="the [viz] extra is not installed (pip install -e '.[viz]')")
from rerun.chunk import RrdReader  # noqa: E402

from memgs_ros.cli import main  # noqa: E402
from memgs_ros.core.gaussians.records import GaussianRecords  # noqa: E402
from memgs_ros.core.map_io.ply import load_ply, save_ply  # noqa: E402
from memgs_ros.errors import ConfigError  # noqa: E402
from memgs_ros.io.image_decoding import decode_compressed_rgb  # noqa: E402
from memgs_ros.viz import RerunTarget  # noqa: E402
from memgs_ros.viz import rerun_log as rl  # noqa: E402
from memgs_ros.viz.splats import psnr_db, sh_rest_rgb, splat_arrays  # noqa: E402

ROW_ID = "rerun.controls.RowId"
CENTERS = "GaussianSplats3D:centers"


def _records(n: int, seed: int = 0) -> GaussianRecords:
    rng = np.random.default_rng(seed)
    return GaussianRecords.from_arrays(np.arange(n) * 7 + 3, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)),
                                       rng.normal(size=(n, 45)) * 0.2, rng.normal(size=n) * 3,
                                       rng.normal(size=(n, 3)) - 3, rng.normal(size=(n, 4)))


def _rows(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every row of every entity in the .rrd at ``path``: {entity: [{column: value}]}, in log order."""
    out: dict[str, list[dict[str, Any]]] = defaultdict(list)
    for chunk in RrdReader(str(path)).stream():
        batch = chunk.to_record_batch()
        cols = {name: (col.cast(pa.int64()) if pa.types.is_timestamp(col.type) else col).to_pylist()
                for name, col in zip(batch.schema.names, batch.columns)}
        for i in range(batch.num_rows):
            out[chunk.entity_path].append({name: values[i] for name, values in cols.items()})
    for rows in out.values():
        rows.sort(key=lambda r: (r.get("frame") or -1, r[ROW_ID]))  # row ids grow with log time
    return out


def _component(rows: list[dict[str, Any]], name: str) -> list[Any]:
    return [r[name] for r in rows if r.get(name) is not None]


def _u32_rgba(colors: np.ndarray) -> np.ndarray:  # [N, 4] uint8 -> [N] packed 0xRRGGBBAA
    c = colors.astype(np.uint32)
    return (c[:, 0] << 24) | (c[:, 1] << 16) | (c[:, 2] << 8) | c[:, 3]


# --------------------------------------------------------------------------- conversion


def test_splats_equal_rerun_own_ply_loader(tmp_path: Path) -> None:
    """Our map as splats == Rerun's own loader reading the same PLY: quaternion order (records
    wxyz, Rerun xyzw), exp of the log-scales, sigmoid opacity, 0.5 + C0 f_dc and the f_rest layout."""
    records = _records(200)
    ply = save_ply(records, tmp_path / "map.ply")
    rrd = tmp_path / "both.rrd"
    rec = RerunTarget(save_path=rrd).open("memgs_test")
    rl.log_map(rec, records, None, sh=True, path="ours")
    rec.log_file_from_path(str(ply), entity_path_prefix="theirs")
    rl.finish(rec)
    rows = _rows(rrd)
    theirs = next(rows[e][-1] for e in rows if e.startswith("/theirs"))
    ours = rows["/ours"][-1]
    np.testing.assert_array_equal(np.array(ours[CENTERS]), np.array(theirs[CENTERS]))
    np.testing.assert_allclose(np.array(ours["GaussianSplats3D:scales"]), np.array(theirs["GaussianSplats3D:scales"]),
                               rtol=1e-6)
    q_ours, q_theirs = np.array(ours["GaussianSplats3D:quaternions"]), np.array(theirs["GaussianSplats3D:quaternions"])
    np.testing.assert_allclose(q_ours * np.sign(q_ours[:, 3:]), q_theirs * np.sign(q_theirs[:, 3:]), atol=1e-6)
    c_ours = np.array(ours["GaussianSplats3D:colors"], dtype=np.int64)
    c_theirs = np.array(theirs["GaussianSplats3D:colors"], dtype=np.int64)
    for shift in (24, 16, 8, 0):  # each RGBA byte within 1 (rounding)
        assert np.abs(((c_ours >> shift) & 255) - ((c_theirs >> shift) & 255)).max() <= 1
    sh_ours = np.array(ours["GaussianSplats3D:sh_coefficients"], dtype=np.float32)
    sh_theirs = np.array(theirs["GaussianSplats3D:sh_coefficients"], dtype=np.float32)
    assert sh_ours.shape == (200, 15, 3)
    np.testing.assert_allclose(sh_ours, sh_theirs, atol=1e-3)  # both stored as float16


def test_splat_arrays_values_and_edge_cases() -> None:
    r = _records(4)
    rot = r.rot.copy()
    rot[0] = 0.0  # a zero quaternion is the identity, not NaN
    opacity = np.array([200.0, -200.0, 0.0, 1.0], np.float32)  # no overflow warning, alpha 255 / 0 / 128
    f_dc = r.f_dc.copy()
    f_dc[1] = [100.0, -100.0, 0.0]  # clipped to [0, 1] before scaling
    r = GaussianRecords.from_arrays(r.ids, r.xyz, f_dc, np.zeros((4, 45)), opacity, r.scale, rot)
    with np.errstate(all="raise"):
        s = splat_arrays(r)
    np.testing.assert_array_equal(s.quaternions_xyzw[0], [0, 0, 0, 1])
    np.testing.assert_allclose(np.linalg.norm(s.quaternions_xyzw, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(s.quaternions_xyzw[2], r.rot[2, [1, 2, 3, 0]] / np.linalg.norm(r.rot[2]), atol=1e-6)
    assert s.colors_rgba[:, 3].tolist() == [255, 0, 128, 186]
    assert s.colors_rgba[1, :3].tolist() == [255, 0, 128]
    np.testing.assert_allclose(s.scales, np.exp(r.scale), rtol=1e-6)
    assert s.sh_rest is None  # a degree-0 map sends no SH
    assert splat_arrays(GaussianRecords.empty()).centers.shape == (0, 3)
    f_rest = np.arange(45, dtype=np.float32)[None]
    assert sh_rest_rgb(f_rest)[0, 2].tolist() == [2.0, 17.0, 32.0]  # coefficient 2 of R, G, B


def test_viz_imports_no_rclpy() -> None:
    """The view's library half runs where ROS does not (memgs view on a laptop)."""
    import subprocess

    code = ("import sys, memgs_ros.viz.rerun_log, memgs_ros.orchestration.saved_run, memgs_ros.core.map_io.follower, "
            "memgs_ros.viz.live_view, "
            "memgs_ros.cli.view; assert 'rclpy' not in sys.modules, 'rclpy imported'")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr


def test_psnr_db() -> None:
    a = np.zeros((4, 4, 3), np.uint8)
    b = a.copy()
    b[0, 0, 0] = 255  # MSE = 1/48 of full scale squared
    assert psnr_db(a, b) == pytest.approx(10 * np.log10(48))
    assert psnr_db(a, a) == float("inf")


def test_rerun_target_checks_its_arguments(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="needs a viewer to spawn, a URL or a file"):
        RerunTarget()
    with pytest.raises(ConfigError, match="rerun\\+http://HOST:9876/proxy"):
        RerunTarget(connect_url="localhost:9876")
    (tmp_path / "dir.rrd").mkdir()
    with pytest.raises(ConfigError, match="is a folder"):
        RerunTarget(save_path=tmp_path / "dir.rrd").check()
    t = RerunTarget(save_path=tmp_path / "run.rrd").for_variant("no_merge")
    assert t.save_path == tmp_path / "run_no_merge.rrd"
    assert t.node_params() == {"spawn": False, "connect_url": "", "save_path": str(tmp_path / "run_no_merge.rrd")}


def test_log_views_pairs_frame_and_render(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    render = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)
    frame = np.repeat(np.repeat(render, 2, axis=0), 2, axis=1)  # full resolution: resized back to the render
    rec = RerunTarget(save_path=tmp_path / "v.rrd").open("memgs_test")
    assert rl.log_views(rec, render, frame, rl.LogTime(3, 10**18), jpeg_quality=0) == float("inf")
    noisy = np.clip(frame.astype(int) + 8, 0, 255).astype(np.uint8)
    value = rl.log_views(rec, render, noisy, rl.LogTime(4, 10**18 + 1), jpeg_quality=90)
    assert value == pytest.approx(psnr_db(np.clip(render.astype(int) + 8, 0, 255).astype(np.uint8), render), abs=0.3)
    assert rl.log_views(rec, render, None, rl.LogTime(5)) is None
    rl.finish(rec)
    rows = _rows(tmp_path / "v.rrd")
    assert len(rows["/views/render"]) == 3 and len(rows["/views/frame"]) == 2
    assert _component(rows["/views/frame"], "EncodedImage:blob")  # the JPEG one
    assert [r["frame"] for r in rows["/quality/psnr_db"]] == [4]  # inf is not plotted


def test_map_follower_follows_deltas_and_repairs_gaps_from_full_maps() -> None:
    """The bridge's and the merger's copy of the map: in step from deltas; a lost delta or a late
    start is repaired by a full map, and the deltas that arrived meanwhile are replayed on top of it."""
    from memgs_ros.core.map_io.follower import MapFollower
    from memgs_ros.core.map_io.map_delta import ApplyStatus, DeltaOutbox, decode

    out = DeltaOutbox(sh_degree=3, tolerance=0.0, epoch=5)
    maps = [_records(50 + 10 * i, seed=0) for i in range(8)]  # grows by 10 Gaussians a step, same ids kept
    deltas = [decode(out.next_delta(m)) for m in maps[:4]]
    f = MapFollower()
    for d in deltas:
        outcome = f.on_delta(d)
        assert outcome.status is ApplyStatus.APPLIED and not outcome.lost_step
    assert f.in_step and f.version == (5, 4, 80)
    np.testing.assert_array_equal(f.replica.records.xyz, maps[3].xyz)

    lost = decode(out.next_delta(maps[4]))  # seq 5 never arrives
    assert lost.seq == 5
    gap = f.on_delta(decode(out.next_delta(maps[5])))  # seq 6: a gap, asks for a full map
    assert gap.lost_step and gap.status is ApplyStatus.GAP and f.resyncing and not f.in_step
    full = decode(out.snapshot(maps[5]))  # the merger's map, unchanged since seq 6 so it keeps seq 6,
    assert full.seq == 6                   # published late:
    held = f.on_delta(decode(out.next_delta(maps[6])))  # seq 7 arrives first and waits
    assert held.status is None and not held.lost_step and f.buffered == 2
    replayed = f.on_full_map(full)
    assert replayed is not None and [(o.seq, o.status) for o in replayed] == [(7, ApplyStatus.APPLIED)]
    assert f.in_step and f.version == (5, 7, 110) and f.buffered == 0
    np.testing.assert_array_equal(f.replica.records.xyz, maps[6].xyz)

    late = MapFollower()  # started mid-run: nothing until a full map
    assert late.on_delta(decode(out.next_delta(maps[7]))).status is ApplyStatus.NEEDS_SNAPSHOT
    assert not late.in_step
    assert late.on_full_map(deltas[0]) is None  # a delta is not a full map
    assert late.on_full_map(decode(out.snapshot(maps[7]))) == ()  # seq 8 again: the map has not changed
    assert late.in_step and late.version == (5, 8, 120)


def test_map_follower_replays_past_a_second_gap_and_reports_unknown_removals() -> None:
    """A gap among the replayed deltas holds the rest back again (none is lost), and a delta
    removing ids the replica never held says how many."""
    from memgs_ros.core.map_io.follower import MapFollower
    from memgs_ros.core.map_io.map_delta import ApplyStatus, DeltaOutbox, decode, message_dtype

    out = DeltaOutbox(sh_degree=3, tolerance=0.0, epoch=1)
    maps = [_records(20 + 5 * i, seed=1) for i in range(7)]
    msgs = [decode(out.next_delta(m)) for m in maps]  # seq 1..7
    f = MapFollower()
    f.on_delta(msgs[0])
    assert f.on_delta(msgs[2]).lost_step  # seq 3: seq 2 lost
    for m in (msgs[3], msgs[5], msgs[6]):  # seq 4, 6, 7 wait (seq 5 lost too)
        f.on_delta(m)
    snapshot = decode(out.snapshot(maps[6]))  # seq 7 (unchanged since): for the second repair
    older = DeltaOutbox(sh_degree=3, tolerance=0.0, epoch=1)
    for m in maps[:3]:
        older.next_delta(m)
    replayed = f.on_full_map(decode(older.snapshot(maps[2])))  # seq 3
    assert replayed is not None and [(o.seq, o.status) for o in replayed] == [
        (4, ApplyStatus.APPLIED), (6, ApplyStatus.GAP), (7, None)]
    assert f.resyncing and f.buffered == 2 and f.replica.seq == 4
    assert f.on_full_map(snapshot) == () and f.in_step and f.version == (1, 7, 50)

    ghost = np.zeros(3, message_dtype(0))  # seq 8 removes two ids nobody ever had; 50 remain
    ghost["op"][0], ghost["op"][1:] = 2, 1
    ghost["id"][0], ghost["id"][1:], ghost["x"][0] = (8 << 32) | 50, [10**6, 10**6 + 1], 1.0  # epoch 1
    outcome = f.on_delta(decode(ghost))
    assert outcome.status is ApplyStatus.APPLIED and outcome.unknown_removals == 2 and f.in_step


# --------------------------------------------------------------------------- memgs view


def _saved_run(folder: Path, n: int = 1500, poses: int = 40) -> GaussianRecords:
    records = _records(n, seed=2)
    save_ply(records, folder / "map.ply")
    lines = ["# timestamp tx ty tz qx qy qz qw"]
    lines += [f"{1000 + i * 0.1:.6f} {0.02 * i:.4f} 0 0 0 {np.sin(i * 0.01):.6f} 0 {np.cos(i * 0.01):.6f}"
              for i in range(poses)]
    (folder / "trajectory.txt").write_text("\n".join(lines) + "\n")
    (folder / "keyframes.txt").write_text("\n".join(lines[::8]) + "\n")  # header + poses 0, 7, 15, ...
    (folder / "stats_timeline.jsonl").write_text(
        '{"t_s": 1.0, "node": "mapper", "gaussians": "10", "iteration": "3", "state": "ok"}\n'
        '{"t_s": 2.0, "node": "mapper", "gaussians": "20", "iteration": "6"}\n')
    return records


def test_view_logs_map_trajectory_keyframes_and_stats(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    records = _saved_run(tmp_path)
    out = tmp_path / "view.rrd"
    assert main(["view", str(tmp_path), "--save", str(out)]) == 0  # a run folder: its map.ply
    assert "1500 Gaussians, 40 poses, 5 keyframes, 2 stats rows" in capsys.readouterr().out
    rows = _rows(out)
    centers = _component(rows["/world/map"], CENTERS)
    assert len(centers) == 1 and len(centers[0]) == len(records) == len(load_ply(tmp_path / "map.ply"))
    np.testing.assert_array_equal(np.array(centers[0]), records.xyz)
    assert len(_component(rows["/world/trajectory"], "LineStrips3D:strips")[0][0]) == 40
    assert len(_component(rows["/world/camera"], "Transform3D:translation")) == 40
    np.testing.assert_allclose(_component(rows["/world/camera"], "Transform3D:translation")[-1], [[0.78, 0, 0]],
                               atol=1e-6)
    keyframes = sorted(e for e in rows if e.startswith("/world/keyframes/"))
    assert keyframes == [f"/world/keyframes/{i:05d}" for i in range(5)]
    assert _component(rows["/world/keyframes/00001"], "Pinhole:image_from_camera")
    assert [r["Scalars:scalars"] for r in rows["/stats/gaussians/mapper"]] == [[10.0], [20.0]]
    assert "/stats/state/mapper" not in rows


def test_view_takes_explicit_files_and_reports_bad_ones(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    _saved_run(tmp_path, n=300, poses=10)
    other = tmp_path / "other"
    other.mkdir()
    (other / "traj.txt").write_text("1.0 0 0 0 0 0 0 1\n2.0 1 0 0 0 0 0 1\n3.0 2 0 0 0 0 0 1\n")
    out = tmp_path / "v.rrd"
    assert main(["view", str(tmp_path / "map.ply"), "--trajectory", str(other / "traj.txt"), "--no-sh",
                 "--save", str(out)]) == 0
    rows = _rows(out)
    assert len(_component(rows["/world/camera"], "Transform3D:translation")) == 3
    assert not _component(rows["/world/map"], "GaussianSplats3D:sh_coefficients")
    capsys.readouterr()
    assert main(["view", str(tmp_path / "map.ply"), "--trajectory", str(tmp_path / "missing.txt"),
                 "--save", str(out)]) == 2
    assert "missing.txt: file not found" in capsys.readouterr().err
    (tmp_path / "bad.ply").write_bytes(b"ply\nformat ascii 1.0\nend_header\n")
    assert main(["view", str(tmp_path / "bad.ply"), "--save", str(out)]) == 2
    assert "not supported" in capsys.readouterr().err


@pytest.mark.filterwarnings("ignore:RRD file has no footer")  # read while the server still writes it
def test_view_streams_to_a_viewer_at_a_url(tmp_path: Path) -> None:
    """--url (as --rerun-url on a run) streams over gRPC: a `rerun` server that saves what it
    receives stands in for the viewer on another machine."""
    import signal
    import socket
    import subprocess
    import time

    records = _saved_run(tmp_path, n=700, poses=12)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    received = tmp_path / "received.rrd"
    # A process group of its own: `python -m rerun` runs the rerun binary as a child, and whatever
    # happens below, the finally ends both (a failed run once left the server running for an hour).
    server = subprocess.Popen([sys.executable, "-m", "rerun", "--port", str(port), "--save", str(received)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)

    def group_alive() -> bool:
        try:
            os.killpg(server.pid, 0)
        except ProcessLookupError:
            return False
        return True

    try:
        end = time.monotonic() + 120  # a busy machine starts it slowly
        while True:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert time.monotonic() < end and server.poll() is None, "the rerun server did not start"
                time.sleep(0.2)
        assert main(["view", str(tmp_path), "--url", f"rerun+http://127.0.0.1:{port}/proxy"]) == 0

        def saved_map() -> int:
            try:
                centers = _component(_rows(received)["/world/map"], CENTERS)
            except Exception:  # noqa: BLE001 - not there yet, or a chunk still being written
                return 0
            return len(centers[0]) if len(centers) == 1 else 0

        end = time.monotonic() + 180  # the server writes what it received as it comes
        while (got := saved_map()) != len(records) and time.monotonic() < end:
            time.sleep(0.2)
    finally:  # not a graceful stop: beside a disk kept busy it took minutes (the file needs no footer)
        if group_alive():
            os.killpg(server.pid, signal.SIGKILL)
        server.wait(timeout=30)
    assert got == len(records), f"the viewer's file holds {got} of the map's {len(records)} Gaussians"


def test_without_rerun_sdk_every_rerun_option_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    """`import rerun` failing (the extra not installed): one line naming the extra, exit 2, and for a
    run nothing started (no logs folder)."""
    _saved_run(tmp_path, n=10, poses=3)
    monkeypatch.setitem(sys.modules, "rerun", None)  # makes `import rerun` raise ImportError
    assert main(["view", str(tmp_path), "--save", str(tmp_path / "v.rrd")]) == 2
    err = capsys.readouterr().err
    assert "memgs_ros[viz]" in err and "Traceback" not in err and err.count("\n") == 1
    out = tmp_path / "run"
    assert main(["run", "--bag", "synthetic:w=32,h=24,n=3", "--out", str(out), "--rerun-save",
                 str(tmp_path / "r.rrd")]) == 2
    assert "memgs_ros[viz]" in capsys.readouterr().err
    assert not (out / "logs").exists()
    assert main(["eval", "synthetic:w=32,h=24,n=3", "--out", str(out), "--rerun-url",
                 "rerun+http://127.0.0.1:9876/proxy"]) == 2
    assert "memgs_ros[viz]" in capsys.readouterr().err


@pytest.mark.ros
def test_bridge_node_refuses_no_sink_and_missing_rerun(context: Any, tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """The node fails at start with one ConfigError (run_node logs it as one fatal line, exit 2)."""
    from rclpy.parameter import Parameter

    from memgs_ros.nodes.rerun_bridge.node import RerunBridgeNode

    with pytest.raises(ConfigError, match="parameters spawn, connect_url, save_path"):
        RerunBridgeNode(context=context)
    with pytest.raises(ConfigError, match="must look like rerun"):
        RerunBridgeNode(context=context, parameter_overrides=[Parameter("connect_url", value="http://x:9876")])
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ConfigError, match=r"memgs_ros\[viz\]"):
        RerunBridgeNode(context=context, parameter_overrides=[Parameter("save_path", value=str(tmp_path / "x.rrd"))])
    assert not (tmp_path / "x.rrd").exists()


# --------------------------------------------------------------------------- end to end


SPEC = "synthetic:w=320,h=240,n=30,seed=3"
# As test_pipeline's FAST: short CPU training, the graph is what is tested.
FAST = {"mapper.iterations_per_frame": 3, "mapper.final_iterations": 150,
        "mapper.mapping.merge_start_iter": 60, "mapper.mapping.merge_interval": 60}


@pytest.mark.ros
@pytest.mark.slow
def test_run_rerun_save_end_to_end(tmp_path: Path, ros_domain_id: int) -> None:
    """`memgs run --rerun-save` over real DDS: the recording's last map is the saved map, and it
    holds every pose, every keyframe, frame/render pairs with their PSNR and the nodes' stats."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed (pip install -e '.[ros]')")
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec
    from memgs_ros.orchestration.run_files import read_summary

    bag = tmp_path / "synthetic.mcap"
    frames = list(generate_frames(parse_spec(SPEC)))
    write_bag(frames, bag)
    rrd, out = tmp_path / "run.rrd", tmp_path / "out"
    sets = [f"{k}={v}" for k, v in FAST.items()] + ["rerun_bridge.map_period_s=2.0"]
    argv = ["run", "--bag", str(bag), "--config", "synthetic", "--out", str(out), "--domain-id", str(ros_domain_id),
            "--namespace", f"/memgs_test_{os.getpid()}_{os.urandom(3).hex()}", "--timeout", "600",
            "--rerun-save", str(rrd)]
    for item in sets:
        argv += ["--set", item]
    assert main(argv) == 0
    s = read_summary(out)
    # Priorities: the tracker first, the mapper below it, the view below the mapper.
    rows_of = [json.loads(line) for line in (out / "stats_timeline.jsonl").read_text().splitlines()]
    assert {int(r["nice"]) for r in rows_of if r["node"] == "rerun_bridge"} == {15}
    assert {int(r["nice"]) for r in rows_of if r["node"] == "mapper"} == {10}
    assert {int(r["nice"]) for r in rows_of if r["node"] == "tracker"} == {0}
    assert s.cpu_s["rerun_bridge"] > 0
    saved = load_ply(s.ply_path)
    rows = _rows(rrd)

    maps = _component(rows["/world/map"], CENTERS)
    assert len(maps) >= 2  # the map grew during the run, not only at the end
    assert len(maps[-1]) == s.gaussians == len(saved) > 1000
    np.testing.assert_array_equal(np.sort(np.array(maps[-1]), axis=0), np.sort(saved.xyz, axis=0))
    # The first pose may go out before DDS has matched the bridge to the tracker (a viewer joining).
    # Every lockstep frame reaches the tracker although the bridge reads the frames too (the
    # player waits for the tracker's readers, not the first reader: it once lost frame 1).
    assert s.poses == 30
    assert s.poses - 1 <= len(_component(rows["/world/camera"], "Transform3D:translation")) <= s.poses
    assert _component(rows["/world/camera"], "Pinhole:image_from_camera")
    assert len([e for e in rows if e.startswith("/world/keyframes/")]) == s.keyframes
    assert len(_component(rows["/world/trajectory"], "LineStrips3D:strips")[-1][0]) >= 2
    renders = _component(rows["/views/render"], "EncodedImage:blob")
    assert renders and _component(rows["/views/frame"], "EncodedImage:blob")
    # The bridge paired renders with their frames (only with frames it kept: a busy, niced bridge
    # drops some, so the last render may have no pair) ...
    assert [v[0] for v in _component(rows["/quality/psnr_db"], "Scalars:scalars")]
    # ... and the recording ends on a render of the final map at the last pose (the runner asks
    # for one): the room, not a blank image (~8-12 dB; CI once ended on an early render, 14.0 dB).
    last = decode_compressed_rgb(SimpleNamespace(format="jpeg", data=np.ravel(renders[-1]).astype(np.uint8)))
    src = cv2.resize(frames[-1].rgb, (last.shape[1], last.shape[0]), interpolation=cv2.INTER_AREA)  # the render's size
    assert psnr_db(last, src) > 15.0
    gaussians = [v[0] for v in _component(rows["/stats/gaussians/mapper"], "Scalars:scalars")]
    assert gaussians and max(gaussians) > 1000
    assert _component(rows["/stats/poses_out/tracker"], "Scalars:scalars")


def test_request_pacer_backs_off_while_unanswered_and_asks_once_at_a_quiet_start() -> None:
    from memgs_ros.core.map_io.follower import RequestPacer

    p = RequestPacer(1.0, max_backoff=8, start_after_s=2.0, started_s=100.0)
    assert not p.ask(101.0, out_of_step=False) and not p.ask(102.0, out_of_step=False)
    assert p.ask(102.1, out_of_step=False)  # nothing heard 2 s after the start: ask once
    assert not p.ask(200.0, out_of_step=False)  # only once
    asked = [t for t in np.arange(300.0, 340.0, 0.5) if p.ask(float(t), out_of_step=True)]
    assert np.diff(asked).tolist() == [2.0, 4.0, 8.0, 8.0, 8.0, 8.0]  # the first at once, then doubling up to 8x
    p.answered()
    assert p.ask(asked[-1] + 8.0, True) and not p.ask(asked[-1] + 9.0, True) and p.ask(asked[-1] + 10.0, True)
    quiet = RequestPacer(1.0, start_after_s=2.0, started_s=0.0)
    quiet.heard()  # a delta came: no start-up request
    assert not quiet.ask(10.0, out_of_step=False)
    plain = RequestPacer(2.0)  # no backoff, no start-up request
    assert plain.ask(0.0, True) and not plain.ask(1.9, True) and plain.ask(2.0, True) and plain.ask(4.0, True)


def test_live_view_times_its_log_calls_on_the_pose_timeline() -> None:
    """The bridge's view without ROS or Rerun: data of a pose's stamp is logged at that frame,
    frusta wait for a camera, keyframes move only past 1 mm, and nothing is logged once closed."""
    from types import SimpleNamespace

    from memgs_ros.core.geometry.camera import PinholeCamera
    from memgs_ros.core.runtime.stat_fields import StatValues
    from memgs_ros.core.runtime.telemetry_fields import ViewFields
    from memgs_ros.viz.live_view import LiveView

    calls: list[tuple] = []

    def fake(name: str):  # noqa: ANN202
        return lambda rec, *args: calls.append((name, *args))

    log = SimpleNamespace(LogTime=lambda frame, stamp=0: (frame, stamp), finish=lambda rec: calls.append(("finish",)),
                          **{n: fake(n) for n in ("log_camera", "log_trajectory", "log_keyframe", "log_map",
                                                  "log_scalars")},
                          log_views=lambda rec, render, frame, t, q: 30.0)
    class _Stats(ViewFields, StatValues):  # the bridge's stats, without a node
        pass

    stats = _Stats()
    view = LiveView(log, "rec", stats, frustum_m=0.1, jpeg_quality=80, log_sh=False, stamps_kept=2)
    T = np.eye(4)
    view.keyframe(500, T)  # before any camera: logged without a frustum
    assert calls[-1] == ("log_keyframe", 0, T, (0, 0), None, 0.1)
    view.keyframe(500, T)  # a repeated copy: nothing
    cam = PinholeCamera(8, 6, 10.0, 10.0, 3.5, 2.5)
    view.set_camera(cam)  # the frustum of the keyframe that waited for it
    assert calls[-1] == ("log_keyframe", 0, T, (0, 0), cam, 0.1)
    for stamp in (1000, 2000, 3000):
        view.pose(stamp, T)
    assert [c[-1] for c in calls if c[0] == "log_camera"] == [cam, None, None]  # the frustum once per camera
    assert view.views(2000, np.zeros((2, 2, 3)), None) == 30.0
    assert view.views(1000, np.zeros((2, 2, 3)), None) == 30.0  # forgotten (2 kept): the latest frame's time
    moved = T.copy()
    moved[0, 3] = 5e-4
    view.keyframes_moved([(500, moved), (999, moved)])  # under 1 mm, and an unknown stamp: nothing
    moved[0, 3] = 2e-3
    view.keyframes_moved([(500, moved)])
    assert calls[-1][0] == "log_keyframe" and calls[-1][3] == (2, 3000)
    assert stats.logged["keyframe"] == 2 and stats.logged["keyframe_moved"] == 1
    assert stats.logged["views"] == 2 and stats.log_us_total >= 0
    view.close()
    n = len(calls)
    view.pose(4000, T)
    assert calls[-1] == ("finish",) and len(calls) == n
