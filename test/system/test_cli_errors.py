"""User mistakes on the command line and in files: exit code 2 and one line on stderr naming the
file and the problem, no traceback, and nothing started (every case fails before a node runs).
Also: nothing is ever unpickled from a user's file."""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import memgs_ros
from memgs_ros.cli import main
from memgs_ros.core.gaussians.gaussian_map import PLY_F_REST, GaussianRecords
from memgs_ros.core.map_io.ply import ids_sidecar_path, load_ply, save_ply
from memgs_ros.errors import DataError

SPEC = "synthetic:w=32,h=24,n=3,seed=1"


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """Good and broken inputs, made once for the module."""
    from memgs_ros.io.bag_writer import write_bag
    from memgs_ros.io.synthetic import generate_frames, parse_spec

    d = tmp_path_factory.mktemp("cli_inputs")
    good = write_bag(generate_frames(parse_spec(SPEC)), d / "good.mcap").path
    raw = good.read_bytes()
    out = {"good_bag": good, "dir": d}
    out["cut_bag"] = d / "cut.mcap"
    out["cut_bag"].write_bytes(raw[: len(raw) // 2])
    out["bad_yaml"] = d / "broken.yaml"
    out["bad_yaml"].write_text("tracker:\n  ros__parameters: [1, 2\n  mapper: }\n")
    out["list_yaml"] = d / "list.yaml"
    out["list_yaml"].write_text("- tracker\n- mapper\n")
    out["section_yaml"] = d / "section.yaml"
    out["section_yaml"].write_text("tracker:\n  ros__parameters: 7\n")
    out["binary_yaml"] = d / "binary.yaml"
    out["binary_yaml"].write_bytes(b"\xff\xfe\x00\x81 not text")
    return out


def _one_line_error(capsys: pytest.CaptureFixture[str], code: int, *fragments: str) -> str:
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1, err
    assert "Traceback" not in err
    for frag in fragments:
        assert frag in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("command", ["run", "eval"])
@pytest.mark.parametrize("config, fragments", [
    ("bad_yaml", ("broken.yaml", "not valid YAML at line 3")),
    ("list_yaml", ("list.yaml", "must be a mapping", "list")),
    ("section_yaml", ("section.yaml", "'tracker'", "ros__parameters")),
    ("binary_yaml", ("binary.yaml", "could not read config")),
    ("no_such_name", ("no config 'no_such_name'",)),
    ("missing/folder/x.yaml", ("missing/folder/x.yaml", "does not exist")),
])
def test_bad_config_is_one_line(command: str, config: str, fragments: tuple[str, ...], files: dict[str, Path],
                                tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = str(files[config]) if config in files else config
    args = ["run", "--bag", SPEC] if command == "run" else ["eval", SPEC]
    code = main([*args, "--config", cfg, "--out", str(tmp_path / "out"), "--timeout", "5"])
    _one_line_error(capsys, code, f"memgs {command}: error:", *fragments)
    assert not (tmp_path / "out" / "params.yaml").exists()  # nothing ran


@pytest.mark.parametrize("source, fragments", [
    ("cut_bag", ("cut.mcap", "cannot read bag")),
    ("nowhere.mcap", ("nowhere.mcap", "no such file or directory")),
    ("synthetic:w=32,bogus=1", ("bad item 'bogus=1'",)),
])
@pytest.mark.parametrize("command", ["run", "eval", "convert"])
def test_bad_source_is_one_line(command: str, source: str, fragments: tuple[str, ...], files: dict[str, Path],
                                tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    src = str(files[source]) if source in files else str(tmp_path / source) if source.endswith(".mcap") else source
    out = tmp_path / "out"
    args = {"run": ["run", "--bag", src, "--out", str(out), "--timeout", "5"],
            "eval": ["eval", src, "--out", str(out), "--timeout", "5"],
            "convert": ["convert", src, str(tmp_path / "o.mcap"), "--no-progress"]}[command]
    code = main(args)
    _one_line_error(capsys, code, *fragments)
    assert not (out / "params.yaml").exists() and not (tmp_path / "o.mcap").exists()


def test_bad_outputs_and_options_are_one_line(files: dict[str, Path], tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    a_file = files["good_bag"]
    code = main(["run", "--bag", SPEC, "--out", str(a_file), "--timeout", "5"])
    _one_line_error(capsys, code, str(a_file), "not a folder")
    code = main(["eval", SPEC, "--out", str(a_file)])
    _one_line_error(capsys, code, str(a_file), "not a folder")
    code = main(["convert", SPEC, str(a_file), "--no-progress"])
    _one_line_error(capsys, code, str(a_file), "already exists")
    code = main(["convert", SPEC, str(a_file / "sub" / "x.mcap"), "--no-progress"])
    _one_line_error(capsys, code, "x.mcap", "cannot create the output")
    code = main(["run", "--bag", SPEC, "--realtime", "--rate", "0", "--out", str(tmp_path / "o")])
    _one_line_error(capsys, code, "--rate")
    code = main(["run", "--bag", SPEC, "--set", "nonode.x=1", "--out", str(tmp_path / "o")])
    _one_line_error(capsys, code, "override 'nonode.x'")


_MISTAKES = [
    (["--set", "tracker.keyframe_max_frames=10"],
     ("tracker has no parameter 'keyframe_max_frames'", "did you mean tracker.keyframe_max_frames?",
      "with --set: tracker.tracker.keyframe_max_frames=...")),
    (["--set", "mapper.mapping.iterationz=3"], ("mapper has no parameter 'mapping.iterationz'",)),
    # Values are checked before anything starts, in the words the node would use at start.
    (["--set", "mapper.mapping.resolution_scale=50.0"],
     ("mapper: parameter 'mapping.resolution_scale' = 50.0 is outside [0.01, 2.0]",)),
    (["--set", "mapper.mapping.resolution_scale=abc"],
     ("parameter 'mapping.resolution_scale' must be of type float", "got 'abc'")),
    (["--set", "mapper.mapping.raster_backend=opengl"], ("'opengl' is not one of",)),
    (["--set", "merger.render_width=0"], ("merger: parameter 'render_width' = 0 is outside [1, 8192]",)),
    (["--set", "mapper.merge.colour_from=oldest"], ("'oldest' is not one of ['older', 'newer']",)),
    (["--kill", "mappr@5"], ("--kill mappr@5", "no node 'mappr'", "did you mean mapper")),
    (["--kill", "mapper@-1"], ("--kill needs NODE@SECONDS",)),
    (["--kill", "mapper@5", "--composed"], ("--kill needs separate processes",)),
]


@pytest.mark.parametrize("command, args, fragments", [
    (command, args, fragments) for command in ("run", "demo", "eval") for args, fragments in _MISTAKES
    if command != "eval" or "--kill" not in args])  # memgs eval has no --kill
def test_mistakes_are_refused_before_anything_is_written(command: str, args: list[str], fragments: tuple[str, ...],
                                                         tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A misspelt parameter or kill target is one line, and no output folder is left behind."""
    out = tmp_path / "out"
    base = {"run": ["run", "--bag", SPEC], "demo": ["demo", "--spec", SPEC], "eval": ["eval", SPEC]}[command]
    code = main([*base, *args, "--out", str(out)])
    _one_line_error(capsys, code, *fragments)
    assert not out.exists()


@pytest.mark.parametrize("config", ["synthetic", "tum_fr1", "tum_fr2", "tum_fr3", "realsense_d435i"])
def test_shipped_configs_name_only_declared_parameters_with_values_in_range(config: str) -> None:
    from memgs_ros.cli.run import check_config

    params = check_config(config)
    assert params["tracker"] and params["mapper"]


def test_a_config_with_a_stray_parameter_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = tmp_path / "stray.yaml"
    cfg.write_text("/**/merger:\n  ros__parameters:\n    save_period: 5.0\n")
    code = main(["run", "--bag", SPEC, "--config", str(cfg), "--out", str(tmp_path / "out")])
    _one_line_error(capsys, code, "merger has no parameter 'save_period'", "save_period_s")


def test_process_prints_no_traceback(files: dict[str, Path], tmp_path: Path) -> None:
    """The real entry point, as a user runs it."""
    res = subprocess.run([sys.executable, "-m", "memgs_ros", "run", "--bag", str(files["cut_bag"]),
                          "--config", str(files["bad_yaml"]), "--out", str(tmp_path / "o")],
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2, res.stderr
    assert "Traceback" not in res.stderr
    assert res.stderr.strip().splitlines() == [res.stderr.strip()]
    assert "broken.yaml" in res.stderr and "not valid YAML" in res.stderr


# ----------------------------------------------------------------------------- PLY files

def _records(n: int) -> GaussianRecords:
    rng = np.random.default_rng(n)
    f = lambda *s: rng.standard_normal(s).astype(np.float32)  # noqa: E731
    return GaussianRecords.from_arrays(np.arange(100, 100 + n, dtype=np.int64), f(n, 3), f(n, 3),
                                       f(n, PLY_F_REST), f(n), f(n, 3), f(n, 4))


def test_operating_system_errors_are_one_line(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture) -> None:
    """Disk full mid-run (or permission denied, a vanished folder): one line naming the file."""
    import memgs_ros.cli.synth as synth

    def full_disk(_args: object) -> int:
        raise OSError(28, "No space left on device", "/data/out/map.ply")

    monkeypatch.setattr(synth, "run", full_disk)
    assert main(["synth", "--out", "x.mcap"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["memgs synth: error: [Errno 28] No space left on device: '/data/out/map.ply'"], err


def test_corrupt_ply_where_evaluation_reads_one(tmp_path: Path) -> None:
    """``memgs eval`` scores the saved map through score_map: a corrupt PLY is a DataError naming it."""
    pytest.importorskip("torch")
    from memgs_ros.core.geometry.camera import PinholeCamera
    from memgs_ros.evaluation.runs import score_map

    p = save_ply(_records(4), tmp_path / "map.ply")
    p.write_bytes(p.read_bytes()[:-10])
    with pytest.raises(DataError, match=r"map\.ply: truncated"):
        score_map(p, {}, np.zeros(0, np.int64), [], PinholeCamera(32, 24, 30.0, 30.0, 16.0, 12.0))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cut=st.integers(0, 4000), flips=st.lists(st.tuples(st.integers(0, 4000), st.integers(1, 255)), max_size=4))
def test_damaged_ply_loads_or_is_a_data_error(tmp_path: Path, cut: int, flips: list[tuple[int, int]]) -> None:
    """Any truncation or byte damage of a PLY (header or body): records or DataError, nothing else."""
    p = tmp_path / "damaged.ply"
    save_ply(_records(3), p, write_ids=False)
    raw = bytearray(p.read_bytes())
    for pos, x in flips:
        if pos < len(raw):
            raw[pos] ^= x
    p.write_bytes(bytes(raw[: len(raw) - min(cut, len(raw))]))
    try:
        rec = load_ply(p)
    except DataError as err:
        assert "damaged.ply" in str(err)
    else:
        assert len(rec.ids) == rec.xyz.shape[0]


# ----------------------------------------------------------------------------- no pickle

def test_ids_sidecar_holding_pickled_objects_is_refused(tmp_path: Path) -> None:
    p = save_ply(_records(3), tmp_path / "m.ply")
    sidecar = ids_sidecar_path(p)
    np.save(sidecar, np.array([object(), 1, 2], dtype=object), allow_pickle=True)
    with pytest.raises(DataError, match=r"m\.ply\.ids\.npy.*(?i:pickle)"):
        load_ply(p)
    sidecar.write_bytes(b"\x93NUMPY garbage")
    with pytest.raises(DataError, match=r"m\.ply\.ids\.npy"):
        load_ply(p)
    np.save(sidecar, np.arange(7))  # a stale sidecar of another map: the PLY wins
    assert load_ply(p).ids.tolist() == [0, 1, 2]


def _calls(tree: ast.AST) -> list[tuple[str, ast.Call]]:
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            name = f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""
            base = f.value.id if isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) else ""
            out.append((f"{base}.{name}" if base else name, node))
    return out


def test_no_loader_in_the_package_can_unpickle() -> None:
    """Every np.load says allow_pickle=False, every torch.load weights_only=True; no pickle,
    marshal or shelve import, no yaml.load / unsafe_load."""
    root = Path(memgs_ros.__file__).parent
    offences: list[str] = []
    np_loads = 0
    for path in sorted(root.rglob("*.py")):
        tree = ast.parse(path.read_text(), filename=str(path))
        where = path.relative_to(root.parent)
        for node in ast.walk(tree):
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                names = [a.name for a in node.names] + ([node.module] if isinstance(node, ast.ImportFrom) else [])
                if any(n and n.split(".")[0] in ("pickle", "marshal", "shelve", "dill", "joblib") for n in names):
                    offences.append(f"{where}:{node.lineno} imports an unpickler")
        for name, call in _calls(tree):
            kw = {k.arg: k.value for k in call.keywords}
            if name in ("np.load", "numpy.load"):
                np_loads += 1
                v = kw.get("allow_pickle")
                if not (isinstance(v, ast.Constant) and v.value is False):
                    offences.append(f"{where}:{call.lineno} np.load without allow_pickle=False")
            elif name == "torch.load":
                v = kw.get("weights_only")
                if not (isinstance(v, ast.Constant) and v.value is True):
                    offences.append(f"{where}:{call.lineno} torch.load without weights_only=True")
            elif name in ("yaml.load", "yaml.unsafe_load", "yaml.full_load"):
                offences.append(f"{where}:{call.lineno} {name}")
    assert np_loads >= 2  # the scan sees the PLY sidecar and checkpoint loaders
    assert not offences, "\n".join(offences)


def test_a_device_or_rasterizer_this_machine_lacks_is_one_line_before_start(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    """What a Jetson user with the wrong torch wheel meets first: mapper.device=cuda without a CUDA
    torch, or the gsplat rasterizer without gsplat (or off CUDA), is one line naming the fix."""
    import torch

    from memgs_ros.core.raster import backends

    monkeypatch.setattr(torch.backends.cuda, "is_built", lambda: False)
    monkeypatch.setattr(backends, "gsplat_available", lambda: False)
    out = tmp_path / "out"
    code = main(["run", "--bag", SPEC, "--set", "mapper.device=cuda", "--out", str(out)])
    _one_line_error(capsys, code, "mapper.device=cuda", "built without CUDA", "install a CUDA build of torch")
    code = main(["eval", SPEC, "--set", "mapper.device=cpu", "--set", "mapper.mapping.raster_backend=gsplat",
                 "--out", str(out)])
    _one_line_error(capsys, code, "raster_backend=gsplat on cpu", "gsplat package is not installed",
                    "pip install '.[gsplat]'")
    monkeypatch.setattr(backends, "gsplat_available", lambda: True)
    code = main(["demo", "--spec", SPEC, "--set", "mapper.device=cpu", "--set",
                 "mapper.mapping.raster_backend=gsplat_packed", "--out", str(out)])
    _one_line_error(capsys, code, "gsplat renders on CUDA")
    code = main(["run", "--bag", SPEC, "--set", "mapper.device=gpu0", "--out", str(out)])
    _one_line_error(capsys, code, "'gpu0' is not a torch device")
    assert not out.exists()


@pytest.mark.parametrize("command", ["run", "eval"])
def test_a_map_bundle_that_does_not_fit_is_one_line(command: str, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """--map is checked against the source before any node starts: missing, another camera, a
    changed file; --mode localize needs a map."""
    from memgs_ros.core.map_io.bundle import MAPPER_FILE, PLY_FILE, TRACKER_FILE, Manifest, commit_bundle, new_staging
    from memgs_ros.io.synthetic import parse_spec

    source_cam = parse_spec(SPEC).camera

    def bundle(fx: float) -> Path:
        staging = new_staging(tmp_path / "maps")
        for f in (PLY_FILE, TRACKER_FILE, MAPPER_FILE):
            (staging / f).write_bytes(f.encode())
        cam = {"width": 32, "height": 24, "fx": fx, "fy": source_cam.fy, "cx": source_cam.cx, "cy": source_cam.cy}
        return commit_bundle(staging, Manifest(0, cam, "rgbd", 1000.0, 3, "map_optical", 3, 1, 1, "", ""))

    args = (["run", "--bag", SPEC] if command == "run" else ["eval", SPEC]) + ["--config", "synthetic",
                                                                              "--timeout", "5"]
    mode = "--mode" if command == "run" else "--map-mode"
    out = tmp_path / "out"
    code = main([*args, "--out", str(out), "--map", str(tmp_path / "nowhere")])
    _one_line_error(capsys, code, "nowhere", "no such folder")
    code = main([*args, "--out", str(out), mode, "localize"])
    _one_line_error(capsys, code, "--mode localize needs --map")
    other = bundle(fx=99.0)
    code = main([*args, "--out", str(out), "--map", str(other)])
    _one_line_error(capsys, code, other.name, "another camera: camera.fx 99.00")
    good = bundle(fx=source_cam.fx)
    (good / TRACKER_FILE).write_bytes(b"changed")
    code = main([*args, "--out", str(out), "--map", str(good)])
    _one_line_error(capsys, code, "tracker.npz is 7 bytes")
    assert not (out / "params.yaml").exists()  # nothing ran
