"""Build the standard ``tf2_msgs`` interface where apt's ROS is absent (the PyPI wheels).

A robot has ``tf2_msgs`` from its ROS install; the PyPI wheels this project tests with do not
ship it, but do ship the rosidl generators, the runtime headers and libraries and
``geometry_msgs``. This module generates ``tf2_msgs/msg/TFMessage`` from its definition
(``geometry_msgs/TransformStamped[] transforms``, as in ros2/geometry2) with the same generators
colcon would call, compiles the C, type-support and Python-extension sources with the system
compiler and installs them where the wheels put theirs (``<prefix>/lib`` and site-packages), so
``/tf`` and ``/tf_static`` carry the real type on real DDS.

    python -m memgs_ros.ros.tf2_msgs_build          # no-op when tf2_msgs already imports
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
from pathlib import Path

PACKAGE = "tf2_msgs"
MSG_DEFINITION = "geometry_msgs/TransformStamped[] transforms\n"
# geometry_msgs depends on these; the generated code includes and links all of them.
DEPENDENCIES = ("geometry_msgs", "std_msgs", "builtin_interfaces")


class InterfaceBuildError(RuntimeError):
    """The interface could not be generated or compiled (the message names the step)."""


def available() -> bool:
    return importlib.util.find_spec(PACKAGE) is not None


def _run(cmd: list[str], step: str) -> None:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise InterfaceBuildError(f"{step} failed:\n{' '.join(cmd)}\n{proc.stderr[-3000:]}")


def _generate(src: Path, out: Path, prefix: Path) -> None:
    """Run the rosidl generators (C, Python, C / Fast DDS / introspection type supports)."""
    os.environ.setdefault("AMENT_PREFIX_PATH", str(prefix))
    try:
        from rosidl_generator_c.cli import GenerateC
        from rosidl_generator_py.cli import GeneratePython
        from rosidl_typesupport_c.cli import GenerateCTypesupport
        from rosidl_typesupport_fastrtps_c.cli import GenerateFastRTPSCTypesupport
        from rosidl_typesupport_introspection_c.cli import GenerateIntrospectionCTypesupport
    except ImportError as exc:
        raise InterfaceBuildError(f"the rosidl generators are not installed ({exc}); "
                                  "pip install -e '.[ros]'") from exc
    files = [f"{src}:msg/TFMessage.msg"]
    include = [str(prefix / "share")]
    for name, cls in (("c", GenerateC), ("py", GeneratePython),
                      ("typesupport_c", GenerateCTypesupport),
                      ("fastrtps_c", GenerateFastRTPSCTypesupport),
                      ("introspection_c", GenerateIntrospectionCTypesupport)):
        cls(name).generate(PACKAGE, files, include, out / name)


def build(prefix: Path | None = None, site_packages: Path | None = None,
          quiet: bool = False) -> Path:
    """Generate, compile and install ``tf2_msgs``; return its Python package folder."""
    prefix = Path(prefix or sys.prefix)
    site_packages = Path(site_packages or sysconfig.get_paths()["purelib"])
    if not (prefix / "include" / "geometry_msgs").is_dir():
        raise InterfaceBuildError(f"no geometry_msgs headers under {prefix}/include: "
                                  "install the ROS wheels (pip install -e '.[ros]')")
    with tempfile.TemporaryDirectory(prefix="memgs_tf2_msgs_") as tmp:
        work = Path(tmp)
        src = work / "src"
        (src / "msg").mkdir(parents=True)
        (src / "msg" / "TFMessage.msg").write_text(MSG_DEFINITION)
        gen = work / "gen"
        noise = io.StringIO()  # the generators name every file they write
        with contextlib.redirect_stdout(noise), contextlib.redirect_stderr(noise):
            try:
                _generate(src, gen, prefix)
            except Exception as exc:
                raise InterfaceBuildError(f"generating the sources failed: {exc}\n{noise.getvalue()[-3000:]}") from exc
        # Headers are included as "tf2_msgs/msg/...": merge the generated trees under one root.
        inc = work / "include" / PACKAGE
        for part in ("c", "fastrtps_c", "introspection_c"):
            shutil.copytree(gen / part / "msg", inc / "msg", dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("*.c", "*.cpp", "*.json"))
        for cmd, step in _compile_steps(gen, work, prefix):
            if not quiet:
                print(f"tf2_msgs: compiling {step}", flush=True)
            _run(cmd, f"compiling {step}")
        pkg = _install_all(gen, work, src, prefix, site_packages)
    importlib.invalidate_caches()
    return pkg


def _compile_steps(gen: Path, work: Path, prefix: Path) -> list[tuple[list[str], str]]:
    """The compiler commands, in order: the C messages, the three type supports, the Python
    conversions, then one Python extension per type support (as colcon's CMake builds them)."""
    cc, cxx = shutil.which("gcc") or shutil.which("cc"), shutil.which("g++") or shutil.which("c++")
    if not cc or not cxx:
        raise InterfaceBuildError("no C/C++ compiler on PATH (gcc, g++)")
    import numpy

    libdir = prefix / "lib"
    includes = [f"-I{work / 'include'}", f"-I{sysconfig.get_paths()['include']}", f"-I{numpy.get_include()}"]
    for dep in [*DEPENDENCIES, "rosidl_runtime_c", "rosidl_typesupport_interface", "rosidl_typesupport_c",
                "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_fastrtps_cpp",
                "rosidl_typesupport_introspection_c", "rosidl_runtime_cpp", "rosidl_dynamic_typesupport",
                "rcutils", "rmw", "rosidl_generator_py", "fastcdr"]:
        if (prefix / "include" / dep).is_dir():
            includes.append(f"-I{prefix / 'include' / dep}")
    includes.append(f"-I{prefix / 'include'}")
    common = ["-shared", "-fPIC", "-O2", f"-L{libdir}", f"-Wl,-rpath,{libdir}", *includes]
    own = [f"-L{work}", f"-l{PACKAGE}__rosidl_generator_c"]

    def lib(name: str) -> str:
        return str(work / f"lib{PACKAGE}__{name}.so")

    def deps(suffix: str) -> list[str]:
        return [f"-l{d}__{suffix}" for d in DEPENDENCIES]

    def files(folder: Path, pattern: str) -> list[str]:
        return sorted(str(p) for p in folder.glob(pattern))

    steps = [
        ([cc, *common, *files(gen / "c" / "msg" / "detail", "*.c"), "-o", lib("rosidl_generator_c"),
          *deps("rosidl_generator_c"), "-lrosidl_runtime_c", "-lrcutils"], "the C messages"),
        ([cxx, *common, "-std=c++17", *files(gen / "fastrtps_c" / "msg" / "detail", "*.cpp"),
          "-o", lib("rosidl_typesupport_fastrtps_c"), *own, *deps("rosidl_typesupport_fastrtps_c"),
          *deps("rosidl_generator_c"), "-lrosidl_typesupport_fastrtps_c", "-lrosidl_typesupport_fastrtps_cpp",
          "-lrosidl_runtime_c", "-lfastcdr", "-lrmw", "-lrcutils"], "the Fast DDS type support"),
        ([cc, *common, *files(gen / "introspection_c" / "msg" / "detail", "*.c"),
          "-o", lib("rosidl_typesupport_introspection_c"), *own, *deps("rosidl_typesupport_introspection_c"),
          *deps("rosidl_generator_c"), "-lrosidl_typesupport_introspection_c", "-lrosidl_runtime_c", "-lrcutils"],
         "the introspection type support"),
        ([cxx, *common, "-std=c++17", *files(gen / "typesupport_c" / "msg", "*.cpp"),
          "-o", lib("rosidl_typesupport_c"), *own, *deps("rosidl_typesupport_c"),
          "-lrosidl_typesupport_c", "-lrosidl_runtime_c", "-lrcutils"], "the C type-support dispatch"),
        ([cc, *common, str(gen / "py" / "msg" / "_tf_message_s.c"), "-o", lib("rosidl_generator_py"), *own,
          *deps("rosidl_generator_py"), *deps("rosidl_generator_c"), "-lrosidl_runtime_c", "-lrcutils"],
         "the Python conversions"),
    ]
    for ts in ("rosidl_typesupport_c", "rosidl_typesupport_fastrtps_c", "rosidl_typesupport_introspection_c"):
        steps.append(([cc, *common, str(gen / "py" / f"_{PACKAGE}_s.ep.{ts}.c"),
                       "-o", str(work / f"{PACKAGE}_s__{ts}.so"), *own, f"-l{PACKAGE}__rosidl_generator_py",
                       f"-l{PACKAGE}__{ts}", *deps("rosidl_generator_py"), *deps("rosidl_generator_c"),
                       "-lrosidl_runtime_c", "-lrosidl_dynamic_typesupport", "-lrosidl_typesupport_c",
                       "-lrmw", "-lrcutils"], f"the Python extension ({ts})"))
    return steps


def _install_all(gen: Path, work: Path, src: Path, prefix: Path, site_packages: Path) -> Path:
    """Libraries beside the wheels' own, the Python package into site-packages, the definition
    under share/ (as colcon lays them out); each library lands by rename."""
    for so in work.glob(f"lib{PACKAGE}__*.so"):
        _install(so, prefix / "lib" / so.name)
    pkg = site_packages / PACKAGE
    staged = work / "pkg"
    shutil.copytree(gen / "py", staged, ignore=shutil.ignore_patterns("*.c"))
    (staged / "__init__.py").touch()
    for so in work.glob(f"{PACKAGE}_s__*.so"):
        shutil.copy2(so, staged / so.name)
    if pkg.exists():
        shutil.rmtree(pkg)
    shutil.copytree(staged, pkg)
    share = prefix / "share" / PACKAGE / "msg"
    share.mkdir(parents=True, exist_ok=True)
    _install(src / "msg" / "TFMessage.msg", share / "TFMessage.msg")
    return pkg


def _install(src: Path, dst: Path) -> None:
    tmp = dst.with_name(f".{dst.name}.tmp")
    shutil.copy2(src, tmp)
    os.replace(tmp, dst)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--force", action="store_true", help="rebuild even if tf2_msgs imports")
    args = ap.parse_args(argv)
    if available() and not args.force:
        print("tf2_msgs: already installed")
        return 0
    try:
        pkg = build()
    except InterfaceBuildError as exc:
        print(f"tf2_msgs: {exc}", file=sys.stderr)
        return 1
    print(f"tf2_msgs: installed {pkg}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
