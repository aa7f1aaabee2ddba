"""Node parameters without a ROS graph: the spec table's rules (the same checks run at start-up
and on ``SetParameters``), ``--help`` of every console script (no ROS started), unknown
arguments and parameters refused, the linkage / diagnostics helpers. The runtime
``SetParameters`` and ``/diagnostics`` tests over DDS are in tests/test_nodes.py."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from converters.edge.nodes import cloud_to_scan_node, converter_node, merger_node
from converters.edge.nodes.common import ERROR, OK, WARN, LatencyWindow, RateMeter, Status
from converters.edge.nodes.params import ParamSpec
from lidarscan.errors import ConfigError

MODULES = {"lidarscan-converter": converter_node, "lidarscan-merger": merger_node,
           "lidarscan-cloud-to-scan": cloud_to_scan_node}
CONFIG = Path(__file__).resolve().parent.parent / "config"


def _all_specs(module: Any) -> list[ParamSpec]:
    specs = module._specs()
    if isinstance(specs[0], ParamSpec):
        return list(specs)
    node, family = specs
    return [*node, *family]


def test_param_spec_checks_type_none_range_and_choices() -> None:
    wait = ParamSpec("max_wait", 2.0, "s", low=0.0)
    assert wait.check(3) == 3.0 and isinstance(wait.check(3), float)  # an int for a float
    for bad in (-5.0, None, "2.0", True, float("nan"), [1.0]):
        with pytest.raises(ConfigError, match="max_wait"):
            wait.check(bad)
    qos = ParamSpec("scan_qos", "sensor_data", "q", choices=("sensor_data", "reliable"))
    assert qos.check("reliable") == "reliable"
    with pytest.raises(ConfigError, match="scan_qos='bogus'.*one of sensor_data"):
        qos.check("bogus")
    count = ParamSpec("max_pending", 16, "n", low=0, high=10)
    assert count.check(0) == 0
    for bad in (2.5, 11, -1, False):
        with pytest.raises(ConfigError, match="max_pending"):
            count.check(bad)
    optional = ParamSpec("slices.NAME.angle_min", None, "NAME first", kind="float")
    assert optional.check(None) is None
    member = optional.for_name("low")
    assert member.name == "slices.low.angle_min" and member.description == "low first"
    names = ParamSpec("names", (), "n", kind="str_list")
    assert names.check(("a", "b")) == ["a", "b"]
    with pytest.raises(ConfigError):
        names.check("ab")
    with pytest.raises(ConfigError):
        ParamSpec("x", object(), "no kind")


@pytest.mark.parametrize("script", sorted(MODULES))
def test_every_default_passes_its_own_rule_and_every_config_key_is_declared(script: str) -> None:
    import yaml

    specs = _all_specs(MODULES[script])
    for spec in specs:
        if spec.default is not None:
            spec.check(spec.default)
    config = {"lidarscan-converter": "converter.yaml", "lidarscan-merger": "merger.yaml",
              "lidarscan-cloud-to-scan": "cloud_to_scan.yaml"}[script]
    data = yaml.safe_load((CONFIG / config).read_text())
    (params,) = (v["ros__parameters"] for v in data.values())

    def flat(d: dict[str, Any], prefix: str = "") -> list[str]:
        out = []
        for k, v in d.items():
            out += flat(v, f"{prefix}{k}.") if isinstance(v, dict) else [prefix + k]
        return out

    templates = [s.name.split(".") for s in specs]
    for key in flat(params):
        parts = key.split(".")
        assert any(len(t) == len(parts) and all(a in (b, "NAME") for a, b in zip(t, parts))
                   for t in templates), f"{config}: {key} is not a parameter of {script}"


def test_converter_settings_come_from_the_same_values_as_the_node() -> None:
    node, per_slice = converter_node._specs()
    values = {s.name: s.default for s in node}
    values["slice_names"] = ["low"]
    values.update({t.for_name("low").name: t.default for t in per_slice})
    with pytest.raises(ConfigError, match="slices.low.min_height"):
        converter_node.settings(values)
    values["slices.low.min_height"], values["slices.low.max_height"] = 0.0, 1.0
    config = converter_node.settings(values)
    assert config["slices"][0].topic == "slices/low" and config["max_wait_ns"] == 2 * 10**9
    core = converter_node.ConverterCore(**{k: v for k, v in config.items()
                                           if k != "extrinsics"})
    core.check(converter_node.probe_info())
    values["slices.low.range_min"], values["slices.low.range_max"] = 5.0, 1.0
    bad = converter_node.settings(values)  # the library's rule, not a copy of it
    bad.pop("extrinsics")
    with pytest.raises(ConfigError, match="range"):
        converter_node.ConverterCore(**bad).check(converter_node.probe_info())


def test_merger_core_reconfigure_rebuilds_or_keeps_everything() -> None:
    node, per_input = merger_node._specs()
    values = {s.name: s.default for s in node}
    values["input_names"] = ["a"]
    values.update({t.for_name("a").name: t.default for t in per_input})
    config = merger_node.settings(values)
    core = merger_node.MergerCore(config["inputs"], jump_back_ns=config["jump_back_ns"],
                                  **config["options"])
    built = core.rebuilds
    values["slop"] = 0.2
    new = merger_node.settings(values)
    core.reconfigure(new["inputs"], jump_back_ns=new["jump_back_ns"], **new["options"])
    assert core.rebuilds == built + 1 and core.merger.slop_ns == 200_000_000
    values["angle_increment"] = 0.0
    worse = merger_node.settings(values)
    with pytest.raises(ConfigError):
        core.reconfigure(worse["inputs"], jump_back_ns=None, **worse["options"])
    assert core.merger.slop_ns == 200_000_000 and core.rebuilds == built + 1  # unchanged
    with pytest.raises(ConfigError, match="input_names"):
        core.reconfigure({"b": {}}, jump_back_ns=None, **new["options"])


# -------------------------------------------------------------------- console scripts, help

def _env() -> dict[str, str]:
    env = dict(os.environ)
    env.pop("_ROS_WHEELS_BOOTSTRAP_COMPLETE", None)
    env["ROS_DOMAIN_ID"] = str(1 + os.getpid() % 100)
    env["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    return env


def _script(name: str) -> list[str]:
    path = Path(sys.executable).parent / name
    return [str(path)] if path.exists() else [sys.executable, "-m", MODULES[name].__name__]


@pytest.mark.parametrize("script", sorted(MODULES))
def test_help_prints_usage_parameters_and_topics_without_starting_ros(script: str) -> None:
    done = subprocess.run(_script(script) + ["--help"], check=False, capture_output=True,
                          text=True, env=_env(), timeout=60)
    assert done.returncode == 0, done.stderr
    out = done.stdout
    assert out.startswith(f"usage: {script}") and "topics" in out and "parameters" in out
    for spec in _all_specs(MODULES[script]):
        assert f"  {spec.name} [" in out and spec.description.split(",")[0] in out
    assert "/diagnostics" in out and "allow_unknown_parameters" in out
    assert "converting" not in out + done.stderr  # the node never started
    # and in-process: no rclpy import at all
    code = (f"import sys; from {MODULES[script].__name__} import main; "
            "rc = main(['x', '-h']); assert rc == 0 and 'rclpy' not in sys.modules")
    check = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True,
                           text=True, env=_env(), timeout=60)
    assert check.returncode == 0, check.stderr


def test_help_into_a_closed_pipe_exits_quietly() -> None:
    """`lidarscan-merger --help | head -1`: the reader is gone before the text is written; the
    script exits 0 without a BrokenPipeError traceback."""
    read_end, write_end = os.pipe()
    os.close(read_end)                                   # nobody reads: the first write fails
    try:
        done = subprocess.run(_script("lidarscan-merger") + ["--help"], check=False,
                              stdout=write_end, stderr=subprocess.PIPE, text=True, env=_env(),
                              timeout=60)
    finally:
        os.close(write_end)
    assert done.returncode == 0 and "BrokenPipeError" not in done.stderr, done.stderr


def test_converter_help_names_the_new_default_topics() -> None:
    text = converter_node.usage()
    assert "lidar_scan" in text and "scan_topic [lidar_scan]" in text
    assert "info_topic [lidar_info]" in text
    assert "cloud_topic [points]" in cloud_to_scan_node.usage()
    assert "scan_topic [lidar_scan]" in cloud_to_scan_node.usage()


def test_unknown_argument_before_ros_args_is_refused() -> None:
    assert converter_node.main(["lidarscan-converter", "--bogus"]) == 2


@pytest.mark.ros
def test_mistyped_parameter_stops_the_console_script_with_a_suggestion() -> None:
    done = subprocess.run(_script("lidarscan-converter") +
                          ["--ros-args", "-p", "target_fram:=base_link"], check=False,
                          capture_output=True, text=True, env=_env(), timeout=60)
    assert done.returncode == 2, done.stderr
    assert "target_fram (did you mean target_frame?)" in done.stderr
    assert "allow_unknown_parameters" in done.stderr and "Traceback" not in done.stderr


@pytest.mark.ros
@pytest.mark.parametrize("module", [converter_node, merger_node, cloud_to_scan_node])
def test_unknown_parameters_refused_unless_allowed(module: Any,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=1 + os.getpid() % 100)
    base = [Parameter("input_names", value=["a"])] if module is merger_node else []
    node = None
    try:
        with pytest.raises(ConfigError, match="slop_typo|slices.lwo|layuot"):
            module._node_class()(context=context, parameter_overrides=base + [
                Parameter({converter_node: "slices.lwo.min_height", merger_node: "slop_typo",
                           cloud_to_scan_node: "layuot"}[module], value=1.0)])
        node = module._node_class()(context=context, parameter_overrides=base + [
            Parameter("slop_typo", value=1.0), Parameter("allow_unknown_parameters",
                                                         value=True)])
        assert not node.has_parameter("slop_typo")
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown(context=context)


@pytest.mark.ros
def test_start_up_values_break_the_same_rules_as_runtime_ones(
        monkeypatch: pytest.MonkeyPatch) -> None:
    rclpy = pytest.importorskip("rclpy")
    from rclpy.parameter import Parameter

    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=1 + os.getpid() % 100)
    try:
        cls = converter_node._node_class()
        for name, value, match in (("max_wait", -5.0, "max_wait=-5.0"),
                                   ("max_wait", "soon", "max_wait='soon'"),
                                   ("scan_qos", "bogus", "scan_qos='bogus'"),
                                   ("pointcloud2.preset", "nope", "preset")):
            with pytest.raises(ConfigError, match=match):
                cls(context=context, parameter_overrides=[Parameter(name, value=value)])
    finally:
        rclpy.try_shutdown(context=context)


# -------------------------------------------------------------------------- diagnostics

def test_status_levels_only_rise_and_collect_reasons() -> None:
    st = Status("linkage", {"pending": 0})
    assert (st.level, st.message) == (OK, "ok")
    st.worse(OK, "nothing")
    st.worse(ERROR, "no LidarInfo")
    st.worse(WARN, "1 dropped")
    assert st.level == ERROR and st.message == "no LidarInfo; 1 dropped"


def test_rate_meter_and_latency_window() -> None:
    now = [0.0]
    meter = RateMeter(clock=lambda: now[0])
    now[0] = 2.0
    delta, dt = meter.update({"scans": 10})
    assert delta == {"scans": 10} and dt == 2.0
    now[0] = 3.0
    assert meter.update({"scans": 15}) == ({"scans": 5}, 1.0)
    window = LatencyWindow(size=3)
    assert window.take() == {}
    for ns in (9_000_000, 1_000_000, 2_000_000, 3_000_000):  # the first one is pushed out
        window.add(ns)
    assert window.take() == {"latency_p50_ms": 2.0, "latency_max_ms": 3.0}
    assert window.take() == {}


def test_merger_defaults_match_the_library_units() -> None:
    node, _ = merger_node._specs()
    values = {s.name: s.default for s in node}
    values["input_names"] = ["a"]
    values.update({t.for_name("a").name: t.default for t in merger_node._specs()[1]})
    options = merger_node.settings(values)["options"]
    assert options["angle_increment"] == pytest.approx(math.radians(0.25))
    assert options["slop_ns"] == 50_000_000 and options["timeout_ns"] == 10**9


def test_a_ctrl_c_inside_a_compiled_callback_of_the_warm_up_is_not_reported() -> None:
    """The report of a KeyboardInterrupt that a C callback could not raise (numba's cache hook
    during a node's warm-up) is dropped; any other unraisable exception is still reported."""
    import sys

    from converters.edge.nodes.common import _interrupts_in_callbacks_quiet

    seen: list[type] = []
    previous = sys.unraisablehook
    sys.unraisablehook = lambda u: seen.append(type(u.exc_value))
    try:
        with _interrupts_in_callbacks_quiet():
            sys.unraisablehook(type("U", (), {"exc_value": KeyboardInterrupt()})())
            sys.unraisablehook(type("U", (), {"exc_value": ValueError()})())
        assert sys.unraisablehook is not previous
    finally:
        sys.unraisablehook = previous
    assert seen == [ValueError]
