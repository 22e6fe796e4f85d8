"""``memgs doctor``: what will run on this machine (torch and CUDA, rasterizer, ROS 2), in one screen."""
from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.metadata
import importlib.util
import json
import os
import platform
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

HELP = "show what will run here: torch/CUDA, the rasterizer the mapper picks, rclpy and DDS"

DEFAULT_RMW = "rmw_fastrtps_cpp"  # what ROS 2 Jazzy loads when RMW_IMPLEMENTATION is unset
JETSON_RELEASE_FILE = Path("/etc/nv_tegra_release")  # present on every JetPack install
# In a child process: importing rclpy exits the process (code 102) when RMW_IMPLEMENTATION
# names a middleware that is not installed, so the probe must not run in ours.
_RCLPY_PROBE = ("import json, rclpy\n"
                "from rclpy.utilities import get_rmw_implementation_identifier as rmw\n"
                "print(json.dumps({'path': rclpy.__file__, 'rmw': rmw()}))")


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--json", action="store_true", help="print the report as one JSON object")
    p.add_argument("--strict", action="store_true",
                   help="exit 1 when something the nodes need is missing or broken (rclpy, rosbags, mcap, "
                        "OpenCV, a gsplat that imports but does not run)")
    p.add_argument("--warm", action="store_true",
                   help="then compile every kernel the nodes run into the kernel cache (a fresh install's first "
                        "run would otherwise compile them while the camera's frames arrive), and print the time")
    p.add_argument("--no-gsplat-check", action="store_true",
                   help="on CUDA, skip rendering a tiny scene with gsplat (its first use may compile its "
                        "CUDA extension: minutes)")


def _dist_version(*names: str) -> str | None:
    """The installed version of the first distribution found among ``names`` (pip metadata)."""
    for name in names:
        with contextlib.suppress(importlib.metadata.PackageNotFoundError):
            return importlib.metadata.version(name)
    return None


def _module(name: str, *dists: str) -> dict[str, Any]:
    """Whether ``name`` imports, and its version (``__version__`` or the distribution's)."""
    try:
        mod = importlib.import_module(name)
    except Exception as err:  # noqa: BLE001 - a broken install fails in any way; report it
        return {"available": False, "version": None, "error": f"{type(err).__name__}: {err}"}
    version = getattr(mod, "__version__", None) or _dist_version(*(dists or (name,)))
    return {"available": True, "version": None if version is None else str(version), "error": None}


def _torch_report() -> dict[str, Any]:
    import torch

    devices: list[dict[str, Any]] = []
    if torch.cuda.is_available():
        for i in range(torch.cuda.device_count()):
            props = torch.cuda.get_device_properties(i)
            devices.append({"index": i, "name": props.name, "memory_gib": round(props.total_memory / 2**30, 1),
                            "compute_capability": f"{props.major}.{props.minor}"})
    return {"version": torch.__version__, "cuda_build": torch.version.cuda,
            "cuda_available": torch.cuda.is_available(), "devices": devices}


def _gsplat_extension_error(device: str) -> str | None:
    """None when a tiny gsplat render (forward and backward) runs on ``device``, else the error."""
    from memgs_ros.core.raster import warm_up

    try:
        # gsplat's build messages go to stdout: keep them out of a --json report.
        with contextlib.redirect_stdout(sys.stderr):
            warm_up(device, "gsplat", sh_degree=0)
    except Exception as err:  # noqa: BLE001 - missing .so, arch mismatch, JIT failure...
        return f"{type(err).__name__}: {str(err).strip().splitlines()[0] if str(err).strip() else ''}"
    return None


def _rclpy_report() -> dict[str, Any]:
    env_rmw = os.environ.get("RMW_IMPLEMENTATION") or None
    report: dict[str, Any] = {"available": False, "version": _dist_version("ros-rclpy", "rclpy"),
                              "path": None, "error": None, "rmw": env_rmw or DEFAULT_RMW,
                              "rmw_source": "RMW_IMPLEMENTATION" if env_rmw else "default"}
    try:
        proc = subprocess.run([sys.executable, "-c", _RCLPY_PROBE], capture_output=True, text=True, timeout=60)
    except subprocess.TimeoutExpired:
        report["error"] = "importing rclpy took over 60 s"
        return report
    if proc.returncode != 0:
        last = (proc.stderr.strip() or f"exit code {proc.returncode}").splitlines()[-1]
        report["error"] = re.sub(r"^(?:\[[^\]]*\]\s*)+:\s*", "", last)  # rcl's "[ERROR] [stamp] [rcl]: " prefix
        return report
    probe = json.loads(proc.stdout.strip().splitlines()[-1])
    report.update(available=True, path=str(Path(probe["path"]).parent), rmw=probe["rmw"])
    if report["version"] is None and os.environ.get("ROS_DISTRO"):
        report["version"] = f"ROS {os.environ['ROS_DISTRO']}"  # apt's rclpy carries no pip metadata
    return report


def _dds_profile(rmw: str) -> dict[str, Any]:
    """The Fast DDS profile the nodes get: the user's, else the package's (memgs run and the launch file)."""
    if "fastrtps" not in rmw:
        return {"file": None, "source": f"not used ({rmw})", "exists": False}
    env_file = os.environ.get("FASTRTPS_DEFAULT_PROFILES_FILE")
    if env_file:
        return {"file": env_file, "source": "FASTRTPS_DEFAULT_PROFILES_FILE", "exists": Path(env_file).is_file()}
    from memgs_ros.errors import ConfigError
    from memgs_ros.orchestration.run_files import config_path

    try:
        packaged = str(config_path("fastdds.xml"))
    except ConfigError:
        return {"file": None, "source": "Fast DDS defaults (the package's fastdds.xml was not found)", "exists": False}
    return {"file": packaged, "source": "memgs run and memgs.launch.py (ros2 run alone: Fast DDS defaults)",
            "exists": True}


def collect(check_gsplat: bool = True) -> dict[str, Any]:
    """Everything ``memgs doctor`` reports, as a JSON-ready dict with ``problems`` (the nodes
    cannot run as installed), ``warnings`` (they run, slower or surprising) and ``verdict``."""
    from memgs_ros.core.mapping.config import MappingConfig
    from memgs_ros.core.raster.backend_choice import choose_backend, device_label, resolve_device
    from memgs_ros.core.raster.gsplat_backend import gsplat_available
    from memgs_ros.core.runtime.cpu import numba_available

    problems: list[str] = []
    warnings: list[str] = []
    torch_info = _torch_report()
    # The mapper's default device ("auto"); not read from nodes.mapper, whose rclpy import would end
    # this process when RMW_IMPLEMENTATION is broken (what the rclpy probe below reports).
    device = resolve_device("auto")
    choice = choose_backend(device, MappingConfig().raster_backend)
    numba_disabled = os.environ.get("MEMGS_DISABLE_NUMBA", "") not in ("", "0")
    gsplat = {"available": gsplat_available(), "version": _dist_version("gsplat"), "cuda_extension": None}
    if gsplat["available"] and torch_info["cuda_available"] and check_gsplat:
        err = _gsplat_extension_error(device)
        gsplat["cuda_extension"] = err or "ok"
        if err:
            problems.append(f"gsplat imports but does not run on CUDA ({err}); the mapper would fail at "
                            "start-up: rebuild it (README 'On a Jetson') or set mapping.raster_backend:=torch")
    backends = {
        "torch": {"available": True},
        "numba": {"available": numba_available(), "version": _dist_version("numba"), "disabled_by_env": numba_disabled},
        "gsplat": gsplat,
    }
    rclpy_info = _rclpy_report()
    packages = {"rosbags": _module("rosbags"), "mcap": _module("mcap"),
                "opencv": _module("cv2", "opencv-python-headless", "opencv-python")}
    for name, info in (("rclpy", rclpy_info), *packages.items()):
        if not info["available"]:
            problems.append(f"{name} is missing or broken: {info['error']}")
    tf2 = {"available": False}
    if rclpy_info["available"]:  # whether TFMessage imports, as the tracker finds out (ros/tf.py)
        from memgs_ros.ros.tf import TF_MISSING, tf_message_type

        tf2["available"] = tf_message_type() is not None
        if not tf2["available"]:
            warnings.append(TF_MISSING)
    if choice.fallback_warning:
        warnings.append("CUDA is present but gsplat is not: the mapper uses the torch fallback rasterizer, "
                        "several times slower; install gsplat: see README 'On a Jetson'")
    if not torch_info["cuda_available"] and JETSON_RELEASE_FILE.exists():
        warnings.append("this is a Jetson but torch sees no CUDA: install NVIDIA's torch wheel for your JetPack "
                        "(README 'On a Jetson'), not PyPI's")
    elif torch_info["cuda_build"] and not torch_info["cuda_available"]:
        warnings.append(f"torch is built for CUDA {torch_info['cuda_build']} but sees no GPU (driver?): "
                        "the mapper runs on the CPU")
    cache = _kernel_cache()
    if numba_available() and not cache["writable"]:
        warnings.append(f"the kernel cache {cache['dir'] or '(numba default)'} is not writable: every node start "
                        "compiles its kernels anew; set NUMBA_CACHE_DIR to a writable folder")
    dds = _dds_profile(rclpy_info["rmw"])
    if dds["file"] and not dds["exists"]:
        warnings.append(f"FASTRTPS_DEFAULT_PROFILES_FILE names a missing file ({dds['file']}): Fast DDS cannot load it")
    if choice.backend == "torch" and device == "cpu" and not numba_disabled:
        warnings.append("numba is not importable: the CPU mapper uses the slower torch compositor (pip install numba)")
    verdict = f"mapper will run on {device_label(device)} with {choice.backend}"
    if choice.backend == "gsplat" and gsplat["cuda_extension"] not in (None, "ok"):
        verdict = f"mapper will FAIL at start-up on {device_label(device)}: gsplat does not run (see ERROR)"
    elif not rclpy_info["available"]:
        verdict = f"the nodes cannot start without rclpy (see ERROR); the {verdict.replace(' will ', ' would ')}"
    return {
        "python": {"version": platform.python_version(), "executable": sys.executable},
        "torch": torch_info,
        "backends": backends,
        "mapper": {"device": device, "device_label": device_label(device), "raster_backend": choice.backend,
                   "requested_backend": choice.requested, "fallback_warning": choice.fallback_warning},
        "ros": {"rclpy": rclpy_info, "rmw_implementation": rclpy_info["rmw"], "rmw_source": rclpy_info["rmw_source"],
                "ros_domain_id": os.environ.get("ROS_DOMAIN_ID"), "dds_profile": dds, "tf2_msgs": tf2},
        "packages": packages,
        "kernel_cache": cache,
        "problems": problems,
        "warnings": warnings,
        "verdict": verdict,
    }


def _kernel_cache() -> dict[str, Any]:
    """numba's cache folder for the nodes (NUMBA_CACHE_DIR; memgs_ros sets a per-user default)
    and whether this user can write it (made if missing)."""
    from memgs_ros.core.kernels import numba_cache_dir

    path = numba_cache_dir()
    writable = False
    if path:
        with contextlib.suppress(OSError):
            Path(path).mkdir(parents=True, exist_ok=True)
        writable = os.access(path, os.W_OK)
    return {"dir": path, "writable": writable}


def _yes(flag: bool) -> str:
    return "yes" if flag else "no"


def _ver(info: dict[str, Any]) -> str:
    return (info["version"] or "installed") if info["available"] else "MISSING"


def format_report(r: dict[str, Any]) -> str:
    """The report as lines of ``key  value``, problems and warnings last, then the verdict."""
    t, b, ros = r["torch"], r["backends"], r["ros"]
    numba, gsplat = b["numba"], b["gsplat"]
    numba_s = (f"{numba['version']}" if numba["available"]
               else "disabled (MEMGS_DISABLE_NUMBA)" if numba["disabled_by_env"] and numba["version"]
               else "not installed")
    gsplat_s = (gsplat["version"] or "installed") if gsplat["available"] else "not installed"
    if gsplat["cuda_extension"] is not None:
        gsplat_s += f", CUDA extension: {gsplat['cuda_extension']}"
    rclpy = ros["rclpy"]
    rclpy_s = f"{_ver(rclpy)} ({rclpy['path']})" if rclpy["available"] else "MISSING (below)"
    domain = ros["ros_domain_id"]
    dds = ros["dds_profile"]
    rows = [
        ("python", f"{r['python']['version']} ({r['python']['executable']})"),
        ("torch", f"{t['version']}, CUDA build {t['cuda_build'] or 'none'}, "
                  f"CUDA available: {_yes(t['cuda_available'])}"),
        *((f"  cuda:{d['index']}", f"{d['name']}, {d['memory_gib']} GiB, compute {d['compute_capability']}")
          for d in t["devices"]),
        ("rasterizer", f"torch: yes | numba: {numba_s} | gsplat: {gsplat_s}"),
        ("mapper", f"device {r['mapper']['device_label']}, raster_backend {r['mapper']['requested_backend']} "
                   f"-> {r['mapper']['raster_backend']}"),
        ("rclpy", rclpy_s),
        ("rmw", f"{ros['rmw_implementation']} ({ros['rmw_source']})"),
        ("tf2_msgs", "yes" if ros["tf2_msgs"]["available"] else "MISSING (no /tf; below)"),
        ("domain", f"ROS_DOMAIN_ID={domain}" if domain is not None
                   else "ROS_DOMAIN_ID unset (0; memgs run picks a free one)"),
        ("dds", f"{dds['file'] or '-'} [{dds['source']}]"
                + ("" if dds["exists"] or not dds["file"] else " MISSING FILE")),
        *((name, _ver(info)) for name, info in r["packages"].items()),
        ("kernels", f"cache {r['kernel_cache']['dir'] or '-'}"
                    + ("" if r["kernel_cache"]["writable"] else " (NOT WRITABLE)")),
    ]
    width = max(len(k) for k, _ in rows)
    lines = [f"{k:<{width}}  {v}" for k, v in rows]
    lines += [f"ERROR: {p}" for p in r["problems"]] + [f"WARNING: {w}" for w in r["warnings"]]
    lines.append(r["verdict"])
    return "\n".join(lines)


def warm(device: str, backend: str, quiet: bool) -> dict[str, Any]:
    """Compile every kernel the nodes run (``core/kernels.py``); per group and total seconds."""
    from memgs_ros.core.kernels import KernelGroup, warm_kernels

    def show(g: KernelGroup) -> None:
        if not quiet:
            print(f"  {g.name:<11} {g.seconds:6.1f} s" + (f"  FAILED: {g.error}" if g.error else ""), flush=True)

    if not quiet:
        print(f"compiling the kernels (loaded from the cache where they are there already) for {device}:", flush=True)
    groups = warm_kernels(device, backend, on_group=show)
    total = round(sum(g.seconds for g in groups), 1)
    if not quiet:
        print(f"kernels warm in {total:.1f} s")
    return {"groups": [{"name": g.name, "seconds": g.seconds, "error": g.error} for g in groups],
            "seconds": total, "ok": all(g.error is None for g in groups)}


def run(args: argparse.Namespace) -> int:
    report = collect(check_gsplat=not args.no_gsplat_check)
    if not args.json:
        print(format_report(report))
    warmed = True
    if args.warm:
        report["warm"] = warm(report["mapper"]["device"], report["mapper"]["raster_backend"], quiet=args.json)
        warmed = report["warm"]["ok"]
    if args.json:
        print(json.dumps(report, indent=2))
    return 1 if (args.strict and report["problems"]) or not warmed else 0
