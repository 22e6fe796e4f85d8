"""``memgs doctor`` reports what really runs here, and the rasterizer choice it shares with the mapper."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from typing import Any

import pytest
import torch

import memgs_ros.core.raster.backend_choice as backend_choice
import memgs_ros.core.raster.backends as backends
from memgs_ros.cli import doctor, main
from memgs_ros.core.runtime.cpu import numba_available


def _expected_backend(numba: bool) -> str:
    """What rasterize(backend="auto") takes on the mapper's default device, written out independently."""
    if torch.cuda.is_available():
        return "gsplat" if backends.gsplat_available() else "torch"
    return "numba" if numba else "torch"


def _doctor_json(**env: str) -> dict[str, Any]:
    proc = subprocess.run([sys.executable, "-m", "memgs_ros", "doctor", "--json", "--no-gsplat-check"],
                          capture_output=True, text=True, timeout=300, env={**os.environ, **env})
    assert proc.returncode == 0, proc.stderr
    return json.loads(proc.stdout)


def test_text_report_names_the_real_versions_and_choice(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["doctor", "--no-gsplat-check"]) == 0
    *lines, verdict = capsys.readouterr().out.strip().splitlines()
    rows = {line.split()[0]: line for line in lines}
    assert f"torch       {torch.__version__}," in rows["torch"]
    assert f"CUDA available: {'yes' if torch.cuda.is_available() else 'no'}" in rows["torch"]
    numba_part = rows["rasterizer"].split("| numba: ")[1].split(" |")[0]
    if numba_available():
        import numba

        assert numba_part == numba.__version__
    else:
        assert numba_part in ("not installed", "disabled (MEMGS_DISABLE_NUMBA)")
    backend = _expected_backend(numba_available())
    assert rows["mapper"].endswith(f"raster_backend auto -> {backend}")
    device = "cuda" if torch.cuda.is_available() else "cpu"
    assert verdict.startswith(f"mapper will run on {device}") and verdict.endswith(f" with {backend}")


def test_doctor_assumes_the_mappers_default_device() -> None:
    """doctor resolves "auto" rather than import the mapper node (rclpy) into its own process."""
    from memgs_ros.nodes.params import MapperParams

    assert MapperParams().device == "auto"


def test_json_report_in_a_fresh_process() -> None:
    r = _doctor_json()
    assert r["torch"]["version"] == torch.__version__
    assert r["torch"]["cuda_build"] == torch.version.cuda
    assert r["torch"]["cuda_available"] is torch.cuda.is_available()
    assert len(r["torch"]["devices"]) == (torch.cuda.device_count() if torch.cuda.is_available() else 0)
    assert r["backends"]["numba"]["available"] is numba_available()
    assert r["mapper"]["raster_backend"] == _expected_backend(numba_available())
    assert r["mapper"]["requested_backend"] == "auto"
    assert r["verdict"].startswith(f"mapper will run on {r['mapper']['device_label']} with ")
    rclpy_info = r["ros"]["rclpy"]
    try:
        import rclpy
    except ImportError:
        assert not rclpy_info["available"] and any(p.startswith("rclpy ") for p in r["problems"])
    else:
        assert rclpy_info["available"] and rclpy_info["path"] == os.path.dirname(rclpy.__file__)
        assert r["ros"]["rmw_implementation"] == os.environ.get("RMW_IMPLEMENTATION", doctor.DEFAULT_RMW)


def test_disabling_numba_makes_the_cpu_choice_torch() -> None:
    r = _doctor_json(MEMGS_DISABLE_NUMBA="1")
    assert r["backends"]["numba"]["available"] is False
    assert r["backends"]["numba"]["disabled_by_env"] is True
    assert r["mapper"]["raster_backend"] == _expected_backend(numba=False)
    if not torch.cuda.is_available():
        assert r["mapper"]["raster_backend"] == "torch" and r["verdict"] == "mapper will run on cpu with torch"


def test_strict_fails_when_rclpy_cannot_start(monkeypatch: pytest.MonkeyPatch,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    # rcl refuses (exits) when RMW_IMPLEMENTATION names a middleware that is not installed; the
    # probe runs in a child process, so doctor itself lives to report it.
    monkeypatch.setenv("RMW_IMPLEMENTATION", "rmw_no_such_middleware_cpp")
    assert main(["doctor", "--no-gsplat-check"]) == 0
    out = capsys.readouterr().out
    assert "rclpy       MISSING" in out and "ERROR: rclpy is missing or broken" in out
    assert "rmw         rmw_no_such_middleware_cpp (RMW_IMPLEMENTATION)" in out
    assert main(["doctor", "--strict", "--no-gsplat-check"]) == 1


@pytest.mark.skipif(backends.gsplat_available(), reason="checks the report of a gsplat that cannot run")
def test_gsplat_check_reports_the_error_instead_of_raising() -> None:
    err = doctor._gsplat_extension_error("cpu")
    assert err is not None and err.startswith("ConfigError: ") and "gsplat" in err


@pytest.mark.parametrize("gsplat, expected, warn", [(True, "gsplat", False), (False, "torch", True)])
def test_auto_on_cuda_takes_gsplat_when_it_imports(monkeypatch: pytest.MonkeyPatch, gsplat: bool, expected: str,
                                                   warn: bool) -> None:
    monkeypatch.setattr(backends, "gsplat_available", lambda: gsplat)
    for device in ("cuda", "cuda:1", torch.device("cuda", 0)):
        choice = backend_choice.choose_backend(device)
        assert (choice.backend, choice.fallback_warning, choice.requested) == (expected, warn, "auto")
    assert backend_choice.choose_backend("cuda", "torch") == backend_choice.BackendChoice("cuda", "torch", "torch",
                                                                                          False)


@pytest.mark.parametrize("numba", [True, False])
def test_auto_on_cpu_takes_numba_when_it_imports(monkeypatch: pytest.MonkeyPatch, numba: bool) -> None:
    monkeypatch.setattr(backends, "gsplat_available", lambda: True)  # never on the CPU
    monkeypatch.setattr(backends, "numba_available", lambda: numba)
    choice = backend_choice.choose_backend("cpu")
    assert (choice.backend, choice.fallback_warning) == ("numba" if numba else "torch", False)
    assert backend_choice.choose_backend("cpu", "gsplat").backend == "gsplat"  # named: taken as asked


def test_resolve_device(monkeypatch: pytest.MonkeyPatch) -> None:
    assert backend_choice.resolve_device("cuda:1") == "cuda:1"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert backend_choice.resolve_device("auto") == "cpu" and backend_choice.device_label("cuda") == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert backend_choice.resolve_device("auto") == "cuda"


def _fake_cuda(monkeypatch: pytest.MonkeyPatch, gsplat: bool) -> None:
    """A machine whose torch sees one GPU, with or without gsplat (the CPU CI has none)."""
    import memgs_ros.core.raster.gsplat_backend as gsplat_backend

    gpu = {"version": torch.__version__, "cuda_build": "12.6", "cuda_available": True,
           "devices": [{"index": 0, "name": "Orin", "memory_gib": 61.4, "compute_capability": "8.7"}]}
    monkeypatch.setattr(doctor, "_torch_report", lambda: gpu)
    monkeypatch.setattr(backend_choice, "resolve_device", lambda requested="auto": "cuda")
    monkeypatch.setattr(backend_choice, "device_label", lambda device: f"{device} (Orin)")
    monkeypatch.setattr(backends, "gsplat_available", lambda: gsplat)
    monkeypatch.setattr(gsplat_backend, "gsplat_available", lambda: gsplat)


def test_cuda_with_only_the_torch_fallback_warns(monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    _fake_cuda(monkeypatch, gsplat=False)
    assert main(["doctor"]) == 0
    *lines, verdict = capsys.readouterr().out.strip().splitlines()
    assert "  cuda:0    Orin, 61.4 GiB, compute 8.7" in lines
    assert any(line.startswith("WARNING: CUDA is present but gsplat is not") and "README 'On a Jetson'" in line
               for line in lines)
    assert verdict == "mapper will run on cuda (Orin) with torch"
    assert not any("gsplat" in p for p in doctor.collect()["problems"])  # slower, not broken: --strict passes


def test_a_gsplat_that_does_not_run_is_an_error(monkeypatch: pytest.MonkeyPatch) -> None:
    _fake_cuda(monkeypatch, gsplat=True)
    monkeypatch.setattr(doctor, "_gsplat_extension_error", lambda device: "RuntimeError: no kernel image for sm_87")
    r = doctor.collect()
    assert r["mapper"]["raster_backend"] == "gsplat" and not r["mapper"]["fallback_warning"]
    assert r["backends"]["gsplat"]["cuda_extension"] == "RuntimeError: no kernel image for sm_87"
    assert any("gsplat imports but does not run" in p for p in r["problems"])
    assert r["verdict"].startswith("mapper will FAIL at start-up on cuda (Orin)")
    monkeypatch.setattr(doctor, "_gsplat_extension_error", lambda device: None)
    r = doctor.collect()
    assert r["backends"]["gsplat"]["cuda_extension"] == "ok" and not any("gsplat" in p for p in r["problems"])
    assert r["verdict"] == "mapper will run on cuda (Orin) with gsplat"


def test_warm_compiles_every_kernel_group_into_the_cache_the_nodes_read() -> None:
    """``memgs doctor --warm``: each group (tracker, rasterizer, SSIM) loads or compiles, the total is
    printed, and the kernels land in NUMBA_CACHE_DIR (the cache the nodes read)."""
    proc = subprocess.run([sys.executable, "-m", "memgs_ros", "doctor", "--warm", "--json", "--no-gsplat-check"],
                          capture_output=True, text=True, timeout=600, env=dict(os.environ))
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    r = json.loads(proc.stdout)
    assert [g["name"] for g in r["warm"]["groups"]] == ["tracker", "rasterizer", "SSIM loss"]
    assert r["warm"]["ok"] and all(g["error"] is None for g in r["warm"]["groups"])
    cache = r["kernel_cache"]["dir"]
    assert cache == os.environ.get("NUMBA_CACHE_DIR", cache) and r["kernel_cache"]["writable"]
    if numba_available():
        assert any(name.endswith(".nbi") for _, _, files in os.walk(cache) for name in files)


def test_the_kernel_cache_is_per_user_unless_numba_cache_dir_says_otherwise(tmp_path) -> None:  # noqa: ANN001
    """numba's default cache sits beside the sources, read-only in an installed package: memgs_ros
    points it at $XDG_CACHE_HOME (or ~/.cache)/memgs_ros/numba, and NUMBA_CACHE_DIR still wins."""
    code = ("import os, memgs_ros, numba.core.config as c; print(os.environ['NUMBA_CACHE_DIR'], c.CACHE_DIR)")
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CACHE_DIR", "XDG_CACHE_HOME")}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**env, "HOME": str(tmp_path)}).stdout.split()
    assert out == [str(tmp_path / ".cache/memgs_ros/numba")] * 2
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**env, "XDG_CACHE_HOME": str(tmp_path / "xdg")}).stdout.split()
    assert out == [str(tmp_path / "xdg/memgs_ros/numba")] * 2
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         env={**env, "NUMBA_CACHE_DIR": str(tmp_path / "mine")}).stdout.split()
    assert out == [str(tmp_path / "mine")] * 2
