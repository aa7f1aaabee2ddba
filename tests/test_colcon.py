"""The checkout as a ROS 2 colcon workspace: manifests, installed layout, launch files.

* ``colcon build`` of a temporary workspace holding this checkout (the sources git tracks)
  builds ``lidarscan_msgs`` (ament_cmake) and ``lidarscan`` (ament_python, package.xml at the
  root) against this environment's ROS 2; the installed layout is what ``ros2 run`` and
  ``ros2 launch`` look for: ``lib/lidarscan/<node>``, ``share/lidarscan/{package.xml,config,
  launch}``, the ament resource index marker, an importable Python package. Built once per
  session (module fixture, 1-3 min on 2 cores).
* ``launch/*.launch.py``: the wheels have no ``launch`` / ``launch_ros`` (and none is on the
  package index), so where they are missing the files run against a recording stub of the few
  classes they use; every node they start must be a console script of pyproject.toml, every
  parameters file must exist and be that node's, every parameter they set must be one the
  file declares, and the pipeline's topics must connect. With a ROS install, the real
  ``launch`` is used.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import subprocess
import sys
import types
from pathlib import Path
from typing import Any

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
LAUNCH_FILES = sorted((ROOT / "launch").glob("*.launch.py"))
NODE_SCRIPTS = ("lidarscan-converter", "lidarscan-merger", "lidarscan-cloud-to-scan")


def real_launch() -> bool:
    """``launch`` and ``launch_ros`` are installed (not this checkout's launch/ directory, which
    Python would import as a namespace package)."""
    try:
        specs = [importlib.util.find_spec(name) for name in ("launch", "launch_ros")]
    except ValueError:  # a stub of ours in sys.modules
        return False
    return all(spec is not None and spec.origin is not None for spec in specs)


REAL_LAUNCH = real_launch()


def console_scripts() -> set[str]:
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        tomllib = pytest.importorskip("tomli")
    return set(tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["scripts"])


# --------------------------------------------------------------------- launch (stub or real)

class Recorded:
    """An object of the stub: its class name and constructor arguments."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        self.args = args
        self.kwargs = kwargs


def stub_modules() -> dict[str, types.ModuleType]:
    """``launch``, ``launch.actions``, ``launch.substitutions``, ``launch_ros.actions``."""
    made: dict[str, types.ModuleType] = {}
    for name, classes in (("launch", ["LaunchDescription"]),
                          ("launch.actions", ["DeclareLaunchArgument"]),
                          ("launch.substitutions", ["LaunchConfiguration"]),
                          ("launch_ros", []), ("launch_ros.actions", ["Node"])):
        module = types.ModuleType(name)
        for cls in classes:
            setattr(module, cls, type(cls, (Recorded,), {}))
        made[name] = module
    return made


def load_launch(path: Path, share: Path, monkeypatch: pytest.MonkeyPatch) -> Any:
    """Run ``generate_launch_description()`` of ``path`` with ``share`` as the package's
    share directory (stub ``launch`` modules when the real ones are missing)."""
    if not REAL_LAUNCH:
        for name, module in stub_modules().items():
            monkeypatch.setitem(sys.modules, name, module)
    import ament_index_python.packages as packages

    def share_directory(package: str) -> str:
        assert package == "lidarscan"
        return str(share)

    monkeypatch.setattr(packages, "get_package_share_directory", share_directory)
    spec = importlib.util.spec_from_file_location(f"launch_{path.name.split('.')[0]}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.generate_launch_description()


def flat_parameters(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` -> ``{"a.b": 1}`` (ROS 2 parameter names)."""
    out: dict[str, Any] = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flat_parameters(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def describe(description: Any) -> tuple[dict[str, str], list[dict[str, Any]]]:
    """Launch arguments {name: default} and, per node, its executable, name, parameters file
    (resolved with the defaults), the file's parameters and the launch file's overrides."""
    entities = description.args[0]
    arguments = {e.args[0]: e.kwargs["default_value"] for e in entities
                 if type(e).__name__ == "DeclareLaunchArgument"}

    def value(v: Any) -> Any:
        if type(v).__name__ == "LaunchConfiguration":
            assert v.args[0] in arguments, f"launch argument {v.args[0]!r} is not declared"
            return arguments[v.args[0]]
        return v

    nodes = []
    for e in entities:
        if type(e).__name__ != "Node":
            continue
        params_file, overrides = e.kwargs["parameters"]
        path = Path(value(params_file))
        document = yaml.safe_load(path.read_text())
        nodes.append({"package": e.kwargs["package"], "executable": e.kwargs["executable"],
                      "name": e.kwargs["name"], "file": path, "file_nodes": list(document),
                      "declared": flat_parameters(document[e.kwargs["name"]]["ros__parameters"]),
                      "overrides": {k: value(v) for k, v in overrides.items()},
                      "namespace": value(e.kwargs["namespace"])})
    return arguments, nodes


def check_nodes(nodes: list[dict[str, Any]], share: Path) -> None:
    scripts = console_scripts()
    for node in nodes:
        assert node["package"] == "lidarscan"
        assert node["executable"] in scripts, node["executable"]
        assert node["file"].is_file() and node["file"].parent == share / "config"
        assert node["file_nodes"] == [node["name"]], "the parameters file is another node's"
        unknown = set(node["overrides"]) - set(node["declared"])
        assert not unknown, f"{node['name']}: parameters not in {node['file'].name}: {unknown}"


def check_pipeline(nodes: list[dict[str, Any]]) -> None:
    """cloud_to_scan -> converter -> merger connect, and no topic loops back."""
    by = {n["name"]: {**n["declared"], **n["overrides"]} for n in nodes}
    c2s, conv, merger = by["lidarscan_cloud_to_scan"], by["lidarscan_converter"], \
        by["lidarscan_merger"]
    assert c2s["scan_topic"] == conv["scan_topic"]
    assert c2s["info_topic"] == conv["info_topic"]
    assert c2s["cloud_topic"] != conv["cloud_topic"], "the converter would feed cloud_to_scan"
    slice_topics = {conv.get(f"slices.{name}.topic", f"slices/{name}")
                    for name in conv["slice_names"]}
    merged = {merger.get(f"inputs.{name}.topic", name) for name in merger["input_names"]}
    assert merged & slice_topics, f"the merger reads none of the slices {slice_topics}"
    assert len({n["namespace"] for n in nodes}) == 1


def test_launch_files_start_the_shipped_nodes_with_their_config(
        monkeypatch: pytest.MonkeyPatch) -> None:
    assert [p.name for p in LAUNCH_FILES] == ["converter.launch.py", "merger.launch.py",
                                              "pipeline.launch.py"]
    if REAL_LAUNCH:  # a ROS install: the real thing
        for path in LAUNCH_FILES:
            description = load_launch(path, ROOT, monkeypatch)
            assert type(description).__name__ == "LaunchDescription"
        return
    started = {}
    for path in LAUNCH_FILES:
        arguments, nodes = describe(load_launch(path, ROOT, monkeypatch))
        check_nodes(nodes, ROOT)
        started[path.name] = sorted(n["executable"] for n in nodes)
    assert started == {"converter.launch.py": ["lidarscan-converter"],
                       "merger.launch.py": ["lidarscan-merger"],
                       "pipeline.launch.py": sorted(NODE_SCRIPTS)}
    _, nodes = describe(load_launch(ROOT / "launch" / "pipeline.launch.py", ROOT, monkeypatch))
    check_pipeline(nodes)


def test_launch_checks_catch_a_wrong_parameter(monkeypatch: pytest.MonkeyPatch) -> None:
    """The checks above fail on a misspelt parameter and on a loop (they can fail)."""
    if REAL_LAUNCH:
        pytest.skip("a real launch is installed: the stub checks are not used")
    _, nodes = describe(load_launch(ROOT / "launch" / "pipeline.launch.py", ROOT, monkeypatch))
    bad = [dict(n, overrides={**n["overrides"], "scan_topik": "x"}) for n in nodes]
    with pytest.raises(AssertionError, match="scan_topik"):
        check_nodes(bad, ROOT)
    loop = [dict(n, overrides={**n["overrides"], "cloud_topic": "points"})
            if n["name"] == "lidarscan_cloud_to_scan" else n for n in nodes]
    with pytest.raises(AssertionError, match="feed cloud_to_scan"):
        check_pipeline(loop)


def test_manifests_name_the_packages_and_build_types() -> None:
    import xml.etree.ElementTree as ET

    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.findtext("name") == "lidarscan"
    assert root.find("export/build_type").text == "ament_python"  # type: ignore[union-attr]
    assert "lidarscan_msgs" in [e.text for e in root.findall("exec_depend")]
    assert (ROOT / "resource" / "lidarscan").is_file()
    msgs = ET.parse(ROOT / "msgs" / "package.xml").getroot()
    assert msgs.findtext("name") == "lidarscan_msgs"
    assert root.findtext("version") == msgs.findtext("version")


# ------------------------------------------------------------------------------ colcon build

def workspace_sources(dest: Path) -> None:
    """Copy the checkout's tracked (and new, not ignored) files to ``dest``."""
    listed = subprocess.run(["git", "ls-files", "-z", "--cached", "--others",
                             "--exclude-standard"], cwd=ROOT, capture_output=True,
                            timeout=60) if shutil.which("git") else None
    if listed is not None and listed.returncode == 0 and listed.stdout:
        for name in listed.stdout.decode().split("\0"):
            source = ROOT / name
            if name and source.is_file():
                (dest / name).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(source, dest / name)
        return
    shutil.copytree(ROOT, dest, ignore=shutil.ignore_patterns(
        ".*", "build", "install", "log", "__pycache__", "*.so", "demo_out"), dirs_exist_ok=True)


def clean_env(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items()
           if k not in ("_ROS_WHEELS_BOOTSTRAP_COMPLETE", "LD_LIBRARY_PATH", "PYTHONPATH")}
    env.update(extra)
    return env


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``colcon build`` of a workspace with this checkout in src/; returns install/."""
    colcon = Path(sys.executable).parent / "colcon"
    if not colcon.exists():
        colcon = Path(shutil.which("colcon") or "")
    missing = [t for t, ok in (("colcon (pip install colcon-common-extensions)",
                                colcon.is_file()),
                               ("cmake", shutil.which("cmake")), ("ninja", shutil.which("ninja")),
                               ("c++", shutil.which("c++"))) if not ok]
    if missing:
        pytest.skip(f"needs {', '.join(missing)} to build a colcon workspace")
    ws = tmp_path_factory.mktemp("colcon_ws")
    src = ws / "src" / "lidarscan"
    workspace_sources(src)
    prefix = str(Path(sys.prefix))
    ament = os.pathsep.join(p for p in (prefix, os.environ.get("AMENT_PREFIX_PATH", "")) if p)
    env = clean_env(AMENT_PREFIX_PATH=ament, CMAKE_PREFIX_PATH=prefix)
    # The root manifest makes the checkout one package to colcon's crawler, which does not look
    # inside a package: msgs/ is a second base path (README, "In a ROS 2 workspace").
    done = subprocess.run(
        [str(colcon), "build", "--base-paths", "src/lidarscan", "src/lidarscan/msgs",
         "--parallel-workers", "1", "--event-handlers", "console_direct-",
         "--cmake-args", "-G", "Ninja", "-DBUILD_TESTING=OFF",
         f"-DPython3_EXECUTABLE={sys.executable}"],
        cwd=ws, env=env, capture_output=True, text=True, timeout=900)
    assert done.returncode == 0, f"colcon build failed:\n{done.stdout[-4000:]}\n" \
                                 f"{done.stderr[-4000:]}"
    return ws / "install"


def site_packages(prefix: Path) -> Path:
    return prefix / "lib" / f"python{sys.version_info[0]}.{sys.version_info[1]}" \
        / "site-packages"


def test_colcon_installs_the_ament_python_layout(installed: Path) -> None:
    pkg = installed / "lidarscan"
    for script in NODE_SCRIPTS + ("lidarscan",):
        exe = pkg / "lib" / "lidarscan" / script   # where `ros2 run lidarscan <exe>` looks
        assert exe.is_file() and os.access(exe, os.X_OK), exe
    share = pkg / "share" / "lidarscan"
    assert (share / "package.xml").read_bytes() == (ROOT / "package.xml").read_bytes()
    assert sorted(p.name for p in (share / "config").iterdir()) == \
        sorted(p.name for p in (ROOT / "config").glob("*.yaml"))
    assert sorted(p.name for p in (share / "launch").iterdir()) == \
        [p.name for p in LAUNCH_FILES]
    assert (pkg / "share" / "ament_index" / "resource_index" / "packages" / "lidarscan").is_file()
    msgs = installed / "lidarscan_msgs"
    assert (msgs / "share" / "ament_index" / "resource_index" / "packages" /
            "lidarscan_msgs").is_file()
    assert (msgs / "include" / "lidarscan_msgs" / "lidarscan_msgs" / "msg" /
            "lidar_scan.hpp").is_file()


def test_colcon_install_runs_from_its_own_prefix(installed: Path) -> None:
    """The installed package (not this checkout) is imported, resolves its share directory
    through the ament index and its CLI runs."""
    paths = os.pathsep.join(str(site_packages(installed / p)) for p in ("lidarscan",
                                                                         "lidarscan_msgs"))
    ament = os.pathsep.join([str(installed / "lidarscan"), str(installed / "lidarscan_msgs"),
                             sys.prefix])
    env = clean_env(PYTHONPATH=paths, AMENT_PREFIX_PATH=ament)
    code = ("import lidarscan, converters, lidarscan_msgs.msg, converters.edge.nodes.converter_node;"
            "from ament_index_python.packages import get_package_prefix, "
            "get_package_share_directory as share;"
            "print(lidarscan.__file__); print(lidarscan_msgs.msg.__file__);"
            "print(get_package_prefix('lidarscan')); print(share('lidarscan'))")
    done = subprocess.run([sys.executable, "-c", code], env=env, cwd=installed,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    module, msg_module, prefix, share = done.stdout.split()
    assert Path(module).is_relative_to(installed / "lidarscan")
    assert Path(msg_module).is_relative_to(installed / "lidarscan_msgs")
    assert Path(prefix) == installed / "lidarscan"
    assert Path(share) == installed / "lidarscan" / "share" / "lidarscan"
    cli = subprocess.run([str(installed / "lidarscan" / "lib" / "lidarscan" / "lidarscan"),
                          "--help"], env=env, cwd=installed, capture_output=True, text=True,
                         timeout=120)
    assert cli.returncode == 0 and "demo" in cli.stdout, cli.stderr


def test_installed_launch_files_find_the_installed_config(installed: Path,
                                                          monkeypatch: pytest.MonkeyPatch
                                                          ) -> None:
    if REAL_LAUNCH:
        pytest.skip("a real launch is installed: covered by the source-tree test")
    share = installed / "lidarscan" / "share" / "lidarscan"
    _, nodes = describe(load_launch(share / "launch" / "pipeline.launch.py", share,
                                    monkeypatch))
    check_nodes(nodes, share)
    check_pipeline(nodes)
