"""launch/memgs.launch.py names only what the colcon install has: every executable is installed,
every file it points at (the default params file, the Fast DDS profile) exists in the package's
share folder, every launch argument it reads is declared, and every parameter it sets (and every
parameter its default params file sets) is declared by the node it goes to.

launch and launch_ros are not on PyPI (reference sec. 9), so the launch file is loaded with small
stand-ins for the few classes it uses, which record their arguments (``load_launch``); the
checker (``check_launch``) works on that record. Its own tests feed it the real launch file with
one name made wrong and expect exactly that name reported. Where launch_ros is importable (a ROS
install) the real description is loaded too and must name the same arguments and executables.
"""
from __future__ import annotations

import importlib.util
import json
import subprocess
import sys
import types
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from xml.etree import ElementTree

import pytest
import yaml
from colcon_install import PKG, REPO, install_env

LAUNCH_NAME = "memgs.launch.py"
LAUNCH_FILE = REPO / "launch" / LAUNCH_NAME
GRAPH = ("tracker", "keyframe_sampler", "mapper", "merger")  # what a robot runs: registry.GRAPH, as a set
COMPOSED = "composed"  # the executable that runs the graph in one process (registry.COMPOSED)
# Declared by rclpy itself on every node.
BUILTIN_PARAMETERS = frozenset({"use_sim_time", "start_type_description_service"})


# ----------------------------------------------------------------------------- stand-ins
class _LaunchConfiguration:
    def __init__(self, variable_name: str, *, default: object = None) -> None:
        self.name = variable_name
        self.default = default

    def perform(self, context: _Context) -> str:
        return context.value(self)


class _Context:
    """What an OpaqueFunction is given: the launch arguments' values (recording undeclared ones)."""

    def __init__(self, launch: Launch) -> None:
        self.launch = launch

    def value(self, config: _LaunchConfiguration) -> str:
        if config.name not in self.launch.arguments:
            self.launch.problems.append(f"undeclared launch argument: {config.name}")
            return str(config.default or "")
        return self.launch.arguments[config.name]


class _OpaqueFunction:
    def __init__(self, *, function: object, args: list[object] | None = None) -> None:
        self.function, self.args = function, list(args or [])


class _DeclareLaunchArgument:
    def __init__(self, name: str, *, default_value: object = None, description: str = "",
                 choices: list[str] | None = None, **_: object) -> None:
        self.name, self.default_value, self.description, self.choices = name, default_value, description, choices


class _ParameterValue:
    def __init__(self, value: object, *, value_type: type | None = None) -> None:
        self.value, self.value_type = value, value_type


class _Node:
    def __init__(self, **kwargs: object) -> None:
        self.kwargs = kwargs


class _IfCondition:
    def __init__(self, predicate_expression: object) -> None:
        self.predicate, self.negate = predicate_expression, False


class _UnlessCondition(_IfCondition):
    def __init__(self, predicate_expression: object) -> None:
        super().__init__(predicate_expression)
        self.negate = True


class _LaunchDescription:
    def __init__(self, initial_entities: list[object] | None = None) -> None:
        self.entities = list(initial_entities or [])


def _stub_modules(share_dirs: Mapping[str, Path]) -> dict[str, types.ModuleType]:
    def get_package_share_directory(package_name: str) -> str:
        if package_name not in share_dirs:
            raise LookupError(f"package '{package_name}' not found")
        return str(share_dirs[package_name])

    spec = {
        "launch": {"LaunchDescription": _LaunchDescription},
        "launch.actions": {"DeclareLaunchArgument": _DeclareLaunchArgument, "OpaqueFunction": _OpaqueFunction},
        "launch.conditions": {"IfCondition": _IfCondition, "UnlessCondition": _UnlessCondition},
        "launch.substitutions": {"LaunchConfiguration": _LaunchConfiguration},
        "launch_ros": {},
        "launch_ros.actions": {"Node": _Node},
        "launch_ros.parameter_descriptions": {"ParameterValue": _ParameterValue},
        "ament_index_python": {},
        "ament_index_python.packages": {"get_package_share_directory": get_package_share_directory},
    }
    modules = {}
    for name, attrs in spec.items():
        mod = types.ModuleType(name)
        mod.__dict__.update(attrs)
        modules[name] = mod
    return modules


@contextmanager
def _modules(replacements: dict[str, types.ModuleType]) -> Iterator[None]:
    saved = {name: sys.modules.get(name) for name in replacements}
    sys.modules.update(replacements)
    try:
        yield
    finally:
        for name, mod in saved.items():
            if mod is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = mod


def _import_launch_file(path: Path) -> types.ModuleType:
    spec = importlib.util.spec_from_file_location(f"launch_under_test_{abs(hash(path))}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# ----------------------------------------------------------------------------- the record
@dataclass
class LaunchedNode:
    package: str
    executable: str
    name: str
    namespace: str
    param_files: list[str]
    params: dict[str, object]  # to every node the process hosts
    env: dict[str, str]
    hosts: tuple[str, ...] = ()  # the nodes the process runs: (name,), or the graph when composed
    sigterm_timeout_s: float = 5.0  # launch's SIGTERM-to-SIGKILL wait (its default: 5 s)
    node_params: dict[str, dict[str, object]] = field(default_factory=dict)  # --param node:param:=value


@dataclass
class Launch:
    arguments: dict[str, str]  # name -> value (default, or the override given)
    nodes: list[LaunchedNode]
    problems: list[str] = field(default_factory=list)


def load_launch(path: Path, share_dirs: Mapping[str, Path], overrides: Mapping[str, str] | None = None) -> Launch:
    """Run ``generate_launch_description()`` of ``path`` with the stand-ins and evaluate it as
    ``ros2 launch ... name:=value`` would (``overrides``)."""
    with _modules(_stub_modules(share_dirs)):
        description = _import_launch_file(path).generate_launch_description()
    assert isinstance(description, _LaunchDescription), type(description)
    overrides = dict(overrides or {})
    launch = Launch(arguments={}, nodes=[])
    for entity in description.entities:
        if isinstance(entity, _DeclareLaunchArgument):
            value = overrides.pop(entity.name, entity.default_value)
            if entity.choices is not None and value not in entity.choices:
                launch.problems.append(f"launch argument {entity.name}={value!r} is not one of {entity.choices}")
            launch.arguments[entity.name] = str(value)
    launch.problems += [f"override of an undeclared launch argument: {name}" for name in overrides]

    def resolve(value: object) -> object:
        if isinstance(value, list):  # substitutions joined, as launch does
            return "".join(str(resolve(v)) for v in value)
        if isinstance(value, _LaunchConfiguration):
            if value.name not in launch.arguments:
                launch.problems.append(f"undeclared launch argument: {value.name}")
                return value.default
            return launch.arguments[value.name]
        if isinstance(value, _ParameterValue):
            raw = resolve(value.value)
            if value.value_type is str or value.value_type is None:
                return str(raw) if value.value_type is str else yaml.safe_load(str(raw))
            parsed = yaml.safe_load(str(raw))
            if not isinstance(parsed, value.value_type):
                launch.problems.append(f"{raw!r} is not a {value.value_type.__name__}")
            return parsed
        return value

    entities: list[object] = []
    for entity in description.entities:  # an OpaqueFunction's entities, made from the arguments
        if isinstance(entity, _OpaqueFunction):
            entities += entity.function(_Context(launch), *entity.args)  # type: ignore[operator]
        else:
            entities.append(entity)
    for entity in entities:
        if isinstance(entity, _DeclareLaunchArgument):
            continue
        if not isinstance(entity, _Node):
            launch.problems.append(f"unexpected launch entity {type(entity).__name__}")
            continue
        kw = entity.kwargs
        condition = kw.get("condition")
        if isinstance(condition, _IfCondition):
            flag = str(resolve(condition.predicate)).lower()
            if flag not in ("true", "false"):
                launch.problems.append(f"condition {flag!r} is not true or false")
            if (flag == "true") == condition.negate:
                continue
        files: list[str] = []
        params: dict[str, object] = {}
        for item in kw.get("parameters") or []:
            if isinstance(item, Mapping):
                params.update({str(k): resolve(v) for k, v in item.items()})
            else:
                files.append(str(resolve(item)))
        if kw.get("remappings"):
            launch.problems.append(f"{kw.get('executable')}: remappings are not checked by this test")
        namespace = str(resolve(kw.get("namespace") or ""))
        if namespace and not namespace.startswith("/"):
            namespace = "/" + namespace  # launch_ros makes a relative namespace absolute
        node_params: dict[str, dict[str, object]] = {}
        if kw.get("ros_arguments"):
            launch.problems.append(f"{kw.get('executable')}: ros_arguments are not checked by this test")
        args = [str(resolve(a)) for a in kw.get("arguments") or []]
        for flag, arg in zip(args[::2], args[1::2]):
            node, sep, rest = arg.partition(":")
            param, eq, value = rest.partition(":=")
            if flag != "--param" or not sep or not eq:
                launch.problems.append(f"{kw.get('executable')}: argument {flag} {arg} is not --param node:param:=value")
                continue
            node_params.setdefault(node, {})[param] = yaml.safe_load(value)
        executable = str(resolve(kw.get("executable")))
        launch.nodes.append(LaunchedNode(
            package=str(resolve(kw.get("package"))), executable=executable,
            name=str(resolve(kw.get("name") or executable)), namespace=namespace,
            param_files=files, params=params,
            env={str(k): str(resolve(v)) for k, v in (kw.get("additional_env") or {}).items()},
            hosts=GRAPH if executable == COMPOSED else (str(resolve(kw.get("name") or executable)),),
            sigterm_timeout_s=float(str(resolve(kw.get("sigterm_timeout") or 5.0))),
            node_params=node_params,
        ))
    return launch


# ----------------------------------------------------------------------------- the checker
def params_file_keys(path: Path, node_name: str) -> set[str]:
    """Parameter names a ROS parameter file sets for ``node_name`` (``/**/name``, ``name``, ``/**``
    sections; nested keys joined with dots)."""
    doc = yaml.safe_load(path.read_text()) or {}
    out: set[str] = set()

    def flatten(d: Mapping, prefix: str = "") -> None:
        for k, v in d.items():
            if isinstance(v, Mapping):
                flatten(v, f"{prefix}{k}.")
            else:
                out.add(f"{prefix}{k}")

    for section, body in doc.items():
        target = str(section).rstrip("/").rsplit("/", 1)[-1]
        if target in (node_name, "*", "**") and isinstance(body, Mapping):
            flatten(body.get("ros__parameters") or {})
    return out


def check_launch(launch: Launch, executables: set[str], declared: Mapping[str, set[str]]) -> list[str]:
    """Everything ``launch`` names that the install lacks: one line each (empty: all present)."""
    problems = list(launch.problems)
    started = sorted(n.executable for n in launch.nodes)
    if started not in (sorted(GRAPH), [COMPOSED]):
        problems.append(f"the launch starts {started}, not the graph {sorted(GRAPH)} (or {COMPOSED!r})")
    for node in launch.nodes:
        if node.package != PKG:
            problems.append(f"{node.executable}: package {node.package!r}, not {PKG!r}")
        if node.executable not in executables:
            problems.append(f"executable {node.executable!r} is not installed")
            continue
        for name in sorted(set(node.node_params) - set(node.hosts)):
            problems.append(f"{node.executable}: parameters for {name!r}, which it does not run")
        for hosted in node.hosts:
            known = declared.get(hosted, set()) | BUILTIN_PARAMETERS
            for name in [*node.params, *node.node_params.get(hosted, {})]:
                if name not in known:
                    problems.append(f"{hosted}: parameter {name!r} is not declared by the node")
            for f in node.param_files:
                if not Path(f).is_file():
                    problems.append(f"{hosted}: params file {f} does not exist")
                    continue
                for name in sorted(params_file_keys(Path(f), hosted) - known):
                    problems.append(f"{hosted}: {Path(f).name} sets {name!r}, which the node does not declare")
        for var, value in node.env.items():
            if value.startswith("/") and not Path(value).is_file():
                problems.append(f"{node.name}: {var}={value} does not exist")
    return sorted(set(problems), key=problems.index)


# ----------------------------------------------------------------------------- checker units (no ROS)
def _declared_by_source() -> dict[str, set[str]]:
    """Stand-in for the nodes' declarations in the units: what the source config and the launch
    file's own parameter names say (the install test asks the nodes themselves)."""
    config = REPO / "config" / "realsense_d435i.yaml"
    declared = {name: params_file_keys(config, name) for name in GRAPH}
    for name in GRAPH:  # every managed node (ros/lifecycle.py)
        declared[name] |= {"autostart"}
    declared["tracker"] |= {"color_topic", "depth_topic", "camera_info_topic"}
    declared["merger"] |= {"map_path", "bundle_dir"}
    declared["mapper"] |= {"checkpoint_path", "map_bundle", "map_mode", "bundle_dir"}
    declared["tracker"] |= {"map_bundle", "map_mode", "bundle_dir"}
    return declared


def _mutated(tmp_path: Path, old: str, new: str) -> Path:
    source = LAUNCH_FILE.read_text()
    assert source.count(old) == 1, f"{old!r} is not in {LAUNCH_FILE} exactly once: update this test"
    path = tmp_path / LAUNCH_NAME
    path.write_text(source.replace(old, new))
    return path


def test_the_launch_file_starts_the_registry_graph() -> None:
    from memgs_ros.nodes.registry import GRAPH as REGISTRY_GRAPH

    assert set(REGISTRY_GRAPH) == set(GRAPH)
    assert {n.name for n in load_launch(LAUNCH_FILE, {PKG: REPO}).nodes} == set(GRAPH)


def test_every_launch_keeps_its_map_in_a_new_folder(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """No relaunch overwrites a map: the PLY and the mapper's checkpoint go into a folder of its own,
    absolute, under $ROS_HOME/memgs, never one an earlier launch made."""
    monkeypatch.setenv("ROS_HOME", str(tmp_path))
    first = load_launch(LAUNCH_FILE, {PKG: REPO})
    run_dir = Path(first.arguments["run_dir"])
    assert run_dir.is_absolute() and run_dir.parent == tmp_path / "memgs"
    by_name = {n.name: n for n in first.nodes}
    assert by_name["merger"].params["map_path"] == str(run_dir / "map.ply")
    assert by_name["mapper"].params["checkpoint_path"] == str(run_dir / "mapper_checkpoint.npz")
    run_dir.mkdir(parents=True)  # the first launch saved something
    second = Path(load_launch(LAUNCH_FILE, {PKG: REPO}).arguments["run_dir"])
    assert second != run_dir and second.parent == run_dir.parent and not second.exists()


@pytest.mark.parametrize("composed", ["false", "true"])
def test_ctrl_c_leaves_the_nodes_time_to_save(composed: str) -> None:
    """launch escalates SIGTERM to SIGKILL after sigterm_timeout: it must cover the mapper's shutdown
    (its checkpoint, then its session's close), or Ctrl-C loses the map's last minutes."""
    pytest.importorskip("rclpy", reason="the ROS extra is not installed")
    from memgs_ros.nodes.mapper.node import SESSION_CLOSE_TIMEOUT_S, SHUTDOWN_SAVE_TIMEOUT_S

    for node in load_launch(LAUNCH_FILE, {PKG: REPO}, {"composed": composed}).nodes:
        assert node.sigterm_timeout_s > SHUTDOWN_SAVE_TIMEOUT_S + SESSION_CLOSE_TIMEOUT_S, node.name


def test_checker_accepts_the_launch_file_against_the_source_tree() -> None:
    launch = load_launch(LAUNCH_FILE, {PKG: REPO})
    assert check_launch(launch, set(GRAPH), _declared_by_source()) == []
    assert launch.arguments["params_file"] == str(REPO / "config" / "realsense_d435i.yaml")
    tracker = next(n for n in launch.nodes if n.name == "tracker")
    assert tracker.params["color_topic"] == "/camera/camera/color/image_raw"
    assert tracker.params["use_sim_time"] is False


CAMERA_TOPIC_PARAMS = ("color_topic", "depth_topic", "camera_info_topic")


def test_a_params_files_topics_win_unless_an_argument_is_given(tmp_path: Path) -> None:
    mine = tmp_path / "mine.yaml"
    mine.write_text("/**/tracker:\n  ros__parameters:\n    color_topic: /drone/rgb\n")
    tracker = next(n for n in load_launch(LAUNCH_FILE, {PKG: REPO}, {"params_file": str(mine)}).nodes
                   if n.name == "tracker")
    assert tracker.param_files == [str(mine)] and not {"color_topic", "depth_topic"} & set(tracker.params)
    given = load_launch(LAUNCH_FILE, {PKG: REPO}, {"params_file": str(mine), "color_topic": "/cam/color"})
    tracker = next(n for n in given.nodes if n.name == "tracker")
    assert tracker.params["color_topic"] == "/cam/color" and "depth_topic" not in tracker.params
    composed = load_launch(LAUNCH_FILE, {PKG: REPO}, {"params_file": str(mine), "composed": "true"}).nodes[0]
    assert not set(CAMERA_TOPIC_PARAMS) & set(composed.node_params.get("tracker", {}))


def test_a_map_to_start_from_reaches_tracker_and_mapper_and_bundles_go_to_the_run_dir() -> None:
    launch = load_launch(LAUNCH_FILE, {PKG: REPO}, {"map": "/data/maps/latest", "map_mode": "localize"})
    by_name = {n.name: n for n in launch.nodes}
    run_dir = launch.arguments["run_dir"]
    for name in ("tracker", "mapper"):
        assert by_name[name].params["map_bundle"] == "/data/maps/latest"
        assert by_name[name].params["map_mode"] == "localize"
    assert {by_name[n].params["bundle_dir"] for n in ("tracker", "mapper", "merger")} == {f"{run_dir}/maps"}
    assert "map_bundle" not in {n.name: n for n in load_launch(LAUNCH_FILE, {PKG: REPO}).nodes}["tracker"].params


@pytest.mark.parametrize(("old", "new", "expected"), [
    ("NODES = GRAPH", 'NODES = tuple("mapping" if n == "mapper" else n for n in GRAPH)',
     "executable 'mapping' is not installed"),
    ('"color_topic": "/camera', '"colour_topic": "/camera', "tracker: parameter 'colour_topic' is not declared"),
    ('"map_path": [LaunchConfiguration', '"map_file": [LaunchConfiguration', "merger: parameter 'map_file' is not declared"),
    ('"realsense_d435i.yaml"', '"realsense_d435.yaml"', "realsense_d435.yaml does not exist"),
    ('LaunchConfiguration("params_file")', 'LaunchConfiguration("param_file")', "undeclared launch argument: param_file"),
    ('"fastdds.xml"', '"fast_dds.xml"', "FASTRTPS_DEFAULT_PROFILES_FILE="),
    ('"package": PACKAGE', '"package": "memgs"', "package 'memgs', not 'memgs_ros'"),
], ids=["executable", "tracker-param", "merger-param", "params-file", "launch-arg", "dds-profile", "package"])
def test_checker_reports_a_wrong_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                      old: str, new: str, expected: str) -> None:
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    problems = check_launch(load_launch(_mutated(tmp_path, old, new), {PKG: REPO}), set(GRAPH), _declared_by_source())
    assert problems, f"{new} went unnoticed"
    assert any(expected in p for p in problems), problems


def test_composed_runs_the_graph_in_one_process_each_node_with_its_own_parameters() -> None:
    launch = load_launch(LAUNCH_FILE, {PKG: REPO}, {"composed": "true", "map_path": "/data/m.ply", "run_dir": "/data"})
    assert [(n.executable, n.hosts) for n in launch.nodes] == [(COMPOSED, GRAPH)]
    (node,) = launch.nodes
    assert node.node_params == {"tracker": {"color_topic": "/camera/camera/color/image_raw",
                                            "depth_topic": "/camera/camera/aligned_depth_to_color/image_raw",
                                            "camera_info_topic": "/camera/camera/color/camera_info",
                                            "bundle_dir": "/data/maps"},
                                "merger": {"map_path": "/data/m.ply", "bundle_dir": "/data/maps"},
                                "mapper": {"checkpoint_path": "/data/mapper_checkpoint.npz",
                                           "bundle_dir": "/data/maps"}}
    assert node.params == {"use_sim_time": False, "autostart": True}  # the parameters every node declares
    assert check_launch(launch, {COMPOSED}, _declared_by_source()) == []
    assert check_launch(launch, set(GRAPH), _declared_by_source()) == ["executable 'composed' is not installed"]


def test_checker_reports_a_composed_parameter_sent_to_the_wrong_node(tmp_path: Path) -> None:
    path = _mutated(tmp_path, '("--param", [f"{node}:{param}:="', '("--param", [f"tracker:{param}:="')
    problems = check_launch(load_launch(path, {PKG: REPO}, {"composed": "true"}), {COMPOSED}, _declared_by_source())
    assert problems == ["tracker: parameter 'map_path' is not declared by the node",
                        "tracker: parameter 'checkpoint_path' is not declared by the node"]


def test_checker_reports_a_params_file_key_no_node_declares(tmp_path: Path) -> None:
    config = tmp_path / "mine.yaml"
    config.write_text((REPO / "config" / "realsense_d435i.yaml").read_text()
                      + "/**/mapper:\n  ros__parameters:\n    mapping.max_mapper_mbyte: 512.0\n")
    launch = load_launch(LAUNCH_FILE, {PKG: REPO}, {"params_file": str(config)})
    assert check_launch(launch, set(GRAPH), _declared_by_source()) == [
        "mapper: mine.yaml sets 'mapping.max_mapper_mbyte', which the node does not declare"]


def test_checker_reports_a_bad_argument_value() -> None:
    launch = load_launch(LAUNCH_FILE, {PKG: REPO}, {"use_sim_time": "yes", "namspace": "/uav1"})
    problems = check_launch(launch, set(GRAPH), _declared_by_source())
    assert any("use_sim_time='yes' is not one of" in p for p in problems), problems
    assert "override of an undeclared launch argument: namspace" in problems


# ----------------------------------------------------------------------------- against the colcon install
# Builds each node of the launch with the arguments launch_ros would give it (its params files,
# then the launch's own parameters as one more file, the namespace) and reports what it declared.
_PROBE = r"""
import importlib, json, sys
import rclpy
from rclpy.node import Node
spec = json.loads(sys.argv[1])
out = {}
for n in spec["nodes"]:
    mod = importlib.import_module("memgs_ros.nodes." + n["executable"] + ".node")
    (cls,) = [c for c in vars(mod).values()
              if isinstance(c, type) and issubclass(c, Node) and c.__module__ == mod.__name__]
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=spec["domain"])
    try:
        from rclpy.parameter import Parameter
        node = cls(context=ctx, cli_args=n["cli_args"],
                   parameter_overrides=[Parameter(k, value=v) for k, v in n["overrides"].items()])
    except Exception as err:
        out[n["name"]] = {"error": f"{type(err).__name__}: {err}"}
    else:
        params = node.get_parameters_by_prefix("")
        out[n["name"]] = {
            "fqn": node.get_fully_qualified_name(),
            "declared": sorted(params),
            "values": {k: node.get_parameter(k).value for k in n["check_values"] if node.has_parameter(k)},
            "save_map": node.resolve_service_name("memgs/save_map"),
        }
        node.destroy_node()
    rclpy.try_shutdown(context=ctx)
print("PROBE" + json.dumps(out))
"""


def probe_nodes(prefix: Path, launch: Launch, workdir: Path, domain: int) -> dict[str, dict]:
    nodes = []
    for i, node in enumerate(launch.nodes):
        own = workdir / f"launch_params_{i}.yaml"
        own.write_text(yaml.safe_dump({"/**": {"ros__parameters": node.params}}))
        cli = ["--ros-args"]
        if node.hosts == (node.name,):
            cli += ["-r", f"__node:={node.name}"]  # one node in the process: launch names it
        if node.namespace:
            cli += ["-r", f"__ns:={node.namespace}"]
        for f in [*node.param_files, str(own)]:
            cli += ["--params-file", f]
        # A composed process runs each hosted node with the process's arguments and its own
        # --param values as the node's parameter overrides (memgs_ros/nodes/composed.py).
        for hosted in node.hosts:
            own_values = node.node_params.get(hosted, {})
            # Unconfigured (autostart off): the parameters are declared and checked at construction;
            # configure's work (the session, the kernels' warm-up) is not what this probes.
            nodes.append({"name": hosted, "executable": hosted, "cli_args": cli,
                          "overrides": {**own_values, "autostart": False},
                          "check_values": sorted({*node.params, *own_values})})
    proc = subprocess.run([sys.executable, "-c", _PROBE, json.dumps({"domain": domain, "nodes": nodes})],
                          env=install_env(prefix, domain), cwd=workdir, capture_output=True, text=True,
                          timeout=300, check=False)
    line = next((ln for ln in proc.stdout.splitlines() if ln.startswith("PROBE")), None)
    assert proc.returncode == 0 and line, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(line[len("PROBE"):])


@pytest.fixture(scope="module")
def installed_share(colcon_prefix: Path, monkeypatch_module: pytest.MonkeyPatch) -> Path:
    """The share folder that ``ros2 launch memgs_ros ...`` looks in: the ament index's answer
    with only the colcon install on AMENT_PREFIX_PATH."""
    packages = pytest.importorskip("ament_index_python.packages", reason="ament_index_python is not installed")
    monkeypatch_module.setenv("AMENT_PREFIX_PATH", str(colcon_prefix / PKG))
    return Path(packages.get_package_share_directory(PKG))


@pytest.fixture(scope="module")
def monkeypatch_module() -> Iterator[pytest.MonkeyPatch]:
    with pytest.MonkeyPatch.context() as mp:
        yield mp


@pytest.mark.ros
def test_launch_file_is_installed_where_ros2_launch_finds_it(colcon_prefix: Path, installed_share: Path) -> None:
    assert installed_share == colcon_prefix / PKG / "share" / PKG
    installed = installed_share / "launch" / LAUNCH_NAME
    assert installed.is_file(), f"{installed} missing (setup.py data_files)"
    assert installed.read_text() == LAUNCH_FILE.read_text()
    depends = {e.text for e in ElementTree.parse(installed_share / "package.xml").getroot().iter("exec_depend")}
    assert {"launch", "launch_ros", "ament_index_python"} <= depends, depends


@pytest.mark.ros
@pytest.mark.slow
def test_installed_launch_names_only_what_the_install_has(colcon_prefix: Path, installed_share: Path,
                                                          tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          ros_domain_id: int) -> None:
    monkeypatch.delenv("FASTRTPS_DEFAULT_PROFILES_FILE", raising=False)
    path = installed_share / "launch" / LAUNCH_NAME
    default = load_launch(path, {PKG: installed_share})
    assert default.arguments["params_file"] == str(installed_share / "config" / "realsense_d435i.yaml")
    # As a robot user would start it: namespaced, on a replayed bag's clock.
    executables = {p.name for p in (colcon_prefix / PKG / "lib" / PKG).iterdir() if p.is_file()}
    for composed in ("false", "true"):
        launch = load_launch(path, {PKG: installed_share},
                             {"namespace": "/uav1", "use_sim_time": "true", "composed": composed})
        _check_installed_launch(colcon_prefix, launch, default, executables, tmp_path / composed, ros_domain_id)


def _check_installed_launch(colcon_prefix: Path, launch: Launch, default: Launch, executables: set[str],
                            tmp_path: Path, domain: int) -> None:
    tmp_path.mkdir()
    report = probe_nodes(colcon_prefix, launch, tmp_path, domain)
    refused = {name: r["error"] for name, r in report.items() if "error" in r}
    assert not refused, f"nodes refused the launch's parameters: {refused}"
    declared = {name: set(r["declared"]) for name, r in report.items()}
    assert check_launch(launch, executables, declared) == []
    assert check_launch(default, executables, declared) == []

    assert {r["fqn"] for r in report.values()} == {f"/uav1/{n}" for n in GRAPH}
    tracker, merger = report["tracker"]["values"], report["merger"]["values"]
    # The launch's topics win over the params file's (relative, so namespaced) ones.
    assert tracker["color_topic"] == "/camera/camera/color/image_raw"
    assert tracker["depth_topic"] == "/camera/camera/aligned_depth_to_color/image_raw"
    assert tracker["camera_info_topic"] == "/camera/camera/color/camera_info"
    assert all(r["values"]["use_sim_time"] is True for r in report.values())
    assert merger["map_path"].endswith("/map.ply") and Path(merger["map_path"]).is_absolute()  # in run_dir
    assert report["merger"]["save_map"] == "/uav1/memgs/save_map"


@pytest.mark.ros
def test_real_launch_ros_loads_the_same_description(installed_share: Path) -> None:
    """On a ROS install: the real launch/launch_ros load the file; it declares the same
    arguments and starts the same executables as the stand-ins recorded."""
    if importlib.util.find_spec("launch_ros") is None:
        pytest.skip("launch_ros is not installed: it is not on PyPI (apt: ros-jazzy-launch-ros); "
                    "the stand-in tests above cover the file")
    from launch import LaunchContext, LaunchDescription  # noqa: I001 (launch/ here is not the package)
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.utilities import normalize_to_list_of_substitutions, perform_substitutions
    from launch_ros.actions import Node

    path = installed_share / "launch" / LAUNCH_NAME
    description = _import_launch_file(path).generate_launch_description()
    assert isinstance(description, LaunchDescription)
    context = LaunchContext()

    def text(value: object) -> str:
        return perform_substitutions(context, normalize_to_list_of_substitutions(value))

    arguments, executables = {}, []
    entities = list(description.entities)
    while entities:
        entity = entities.pop(0)
        if isinstance(entity, DeclareLaunchArgument):
            arguments[entity.name] = text(entity.default_value)
            context.launch_configurations[entity.name] = arguments[entity.name]
        elif isinstance(entity, OpaqueFunction):  # the nodes, made once the arguments are known
            entities[:0] = entity.execute(context) or []
        elif isinstance(entity, Node):
            assert text(entity.node_package) == PKG
            executables.append(text(entity.node_executable))
    recorded = load_launch(path, {PKG: installed_share})
    assert arguments == recorded.arguments
    assert sorted(executables) == sorted(n.executable for n in recorded.nodes)
