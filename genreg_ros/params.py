"""register_node's ROS parameters, derived from `genreg_ros.config.SETTINGS` (nothing is listed here); the
only settings module that imports rclpy.

Each setting becomes one parameter of the same dotted name: its ROS type follows the field's type, its
descriptor carries the help, the range and read_only (start-up settings). Values are validated by building
a `NodeConfig` from them, so the dataclasses' own checks (ranges, choices, cross-field rules) are the
node's. ROS has no None: an optional integer is -1 when None (registration.seed), an optional list is []
(preprocess.crop_min / crop_max); `genreg_ros.config.to_ros` / `from_ros` are those converters. A params file is checked
before rcl reads it: unknown keys, wrong types and invalid values are one-line errors.
"""

from __future__ import annotations

import difflib
import fnmatch
import math
from collections.abc import Callable, Iterator
from typing import Any

import yaml
from rcl_interfaces.msg import (
    FloatingPointRange,
    IntegerRange,
    ParameterDescriptor,
    ParameterType,
    SetParametersResult,
)
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter

from genreg_core.config import Setting, settings
from genreg_core.errors import ConfigError
from genreg_ros.config import (
    DOUBLE_ARRAY,
    SETTINGS,
    NodeConfig,
    from_ros,
    node_config,
    optional_type,
    ros_kind,
    to_ros,
)

ROS_TYPES = {
    bool: (ParameterType.PARAMETER_BOOL, "bool"),
    int: (ParameterType.PARAMETER_INTEGER, "integer"),
    float: (ParameterType.PARAMETER_DOUBLE, "double"),
    str: (ParameterType.PARAMETER_STRING, "string"),
    DOUBLE_ARRAY: (ParameterType.PARAMETER_DOUBLE_ARRAY, "list of doubles"),
}
INT_LIMIT = 2**31 - 1  # the ROS range of an integer setting without a declared bound
BUILTIN = ("use_sim_time", "start_type_description_service", "qos_overrides.*")  # rclpy's own parameters
BY_NAME = {s.name: s for s in SETTINGS}


class ParamError(ValueError):
    """A parameter value or a params file is invalid; the message is one line."""


# ----------------------------------------------------------------------------- setting <-> ROS parameter
def ros_range(s: Setting) -> tuple[float, float] | None:
    """The inclusive ROS range of a numeric setting (an optional integer's None is -1), or None."""
    kind, optional = ros_kind(s), optional_type(s.type)[1]
    if kind is int and (optional or s.low is not None or s.high is not None):
        low = -1 if optional else (-INT_LIMIT if s.low is None else s.low)
        return low, INT_LIMIT if s.high is None else s.high
    if kind is float and (s.low is not None or s.high is not None):
        return (-math.inf if s.low is None else s.low), (math.inf if s.high is None else s.high)
    return None


def check_type(s: Setting, value: Any) -> str | None:
    """Why `value` is not a valid ROS value of setting `s` (type, finiteness, ROS range), or None."""
    kind = ros_kind(s)
    if kind is DOUBLE_ARRAY:
        if value is None:
            return None
        if not isinstance(value, (list, tuple)) or not all(
            isinstance(v, float) or (isinstance(v, int) and not isinstance(v, bool)) for v in value
        ):
            return f"{s.name} must be a list of numbers"
        return None if all(math.isfinite(v) for v in value) else f"{s.name} must hold finite numbers"
    if not isinstance(value, kind) or (kind is not bool and isinstance(value, bool)):
        hint = " (write 1.0, not 1)" if kind is float and isinstance(value, int) else ""
        return f"{s.name} must be a {ROS_TYPES[kind][1]}{hint}, got {value!r}"
    if kind is float and not math.isfinite(value):
        return f"{s.name} must be finite"
    bounds = ros_range(s)
    if bounds is not None and not bounds[0] <= value <= bounds[1]:
        return f"{s.name} must be in [{bounds[0]:g}, {bounds[1]:g}], got {value!r}"
    return None


def to_config(values: dict[str, Any]) -> NodeConfig:
    """The NodeConfig of ROS parameter values (every setting's name; missing ones keep their default).
    ConfigError names the first invalid setting."""
    return node_config({s.name: from_ros(s, values[s.name]) for s in SETTINGS if s.name in values})


def ros_values(config: NodeConfig) -> dict[str, Any]:
    """Every setting of `config` as ROS parameter values, by name."""
    return {s.name: to_ros(s, s.default) for s in settings(config)}


def descriptor(s: Setting) -> ParameterDescriptor:
    extra = f" One of: {', '.join(s.choices)}." if s.choices else ""
    d = ParameterDescriptor(name=s.name, type=ROS_TYPES[ros_kind(s)][0], description=s.help + extra,
                            read_only=s.start_up)
    bounds = ros_range(s)
    if bounds is not None and ros_kind(s) is int:
        d.integer_range = [IntegerRange(from_value=int(bounds[0]), to_value=int(bounds[1]), step=0)]
    elif bounds is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(bounds[0]), to_value=float(bounds[1]))]
    return d


# ----------------------------------------------------------------------------- declaration and validation
def declare(node: Node) -> NodeConfig:
    """Declare every parameter on `node` and return the config they give; ParamError on a bad value."""
    values: dict[str, Any] = {}
    for s in SETTINGS:
        try:
            if ros_kind(s) is DOUBLE_ARRAY:  # an empty default has no type of its own
                param = node.declare_parameter(s.name, Parameter.Type.DOUBLE_ARRAY, descriptor(s))
                if param.value is None:  # rcl reads `[]` in YAML as "not set"
                    node.set_parameters([Parameter(s.name, Parameter.Type.DOUBLE_ARRAY, to_ros(s, s.default))])
                value = list(node.get_parameter(s.name).value or [])
            else:
                value = node.declare_parameter(s.name, to_ros(s, s.default), descriptor(s)).value
        except ParameterException as exc:  # rclpy's type/range errors: turn them into one line
            raise ParamError(f"parameter {s.name}: {_one_line(exc)}") from None
        values[s.name] = value
    return build(values)


def merged(config: NodeConfig, params: list[Parameter]) -> NodeConfig:
    """`config` with the node's parameters among `params` applied; ParamError if invalid."""
    values = ros_values(config)
    for p in params:
        s = BY_NAME.get(p.name)
        if s is not None:  # else use_sim_time or another rclpy parameter
            values[p.name] = list(p.value or []) if ros_kind(s) is DOUBLE_ARRAY else p.value
    return build(values)


def build(values: dict[str, Any], where: str = "") -> NodeConfig:
    """`to_config` after checking each value's ROS type; ParamError (prefixed by `where`) names the first
    bad value."""
    for name, value in values.items():
        reason = check_type(BY_NAME[name], value)
        if reason:
            raise ParamError(where + reason)
    try:
        return to_config(values)
    except ConfigError as exc:
        raise ParamError(where + str(exc)) from None


# Parameters the node no longer has -> what replaced them (said instead of a guess at a similar name).
REMOVED = {"sync.time_jump": "removed: a stamp more than sync.slop older than the newest of its topic resets pairing",
           "map.lost_confidence": "removed: a scan is a miss when its pose is not published (min_confidence)",
           "target_crop_radius": "removed: use map.enabled (map mode localises scans in a large map, target_file "
                                 "or a latched target_cloud, and crops it around the pose itself)"}


def unknown_text(name: str) -> str:
    """"unknown parameter 'x' (did you mean y?)": the one wording for -p, params files and overrides."""
    if name in REMOVED:
        return f"unknown parameter '{name}' ({REMOVED[name]})"
    near = [n for n in BY_NAME if n.split(".")[-1] == name.split(".")[-1]]
    near = near or difflib.get_close_matches(name, list(BY_NAME), n=1, cutoff=0.8)
    return f"unknown parameter '{name}'" + (f" (did you mean {near[0]}?)" if near else "")


def check_overrides(node: Node) -> None:
    """ParamError naming the first parameter given to `node` (-p, a params file, parameter_overrides) that
    it does not declare; rclpy itself ignores them silently. Call after `declare`."""
    for name in node._parameter_overrides:  # rclpy keeps the overrides there (no public accessor)
        if not node.has_parameter(name) and not any(fnmatch.fnmatchcase(name, b) for b in BUILTIN):
            raise ParamError(unknown_text(name))


def coerce_arrays(params: list[Parameter]) -> list[Parameter]:
    """A pre-set callback: an empty array of any type (what `ros2 param set NODE initial_guess []` sends: a
    bool array) or an integer array for a list-of-doubles setting becomes a double array."""
    out = []
    for p in params:
        s = BY_NAME.get(p.name)
        if s is not None and ros_kind(s) is DOUBLE_ARRAY and isinstance(p.value, (list, tuple)) and (
            len(p.value) == 0 or p.type_ == Parameter.Type.INTEGER_ARRAY
        ):
            p = Parameter(p.name, Parameter.Type.DOUBLE_ARRAY, [float(v) for v in p.value])
        out.append(p)
    return out


def make_validator(current: Callable[[], NodeConfig]):
    """An on-set-parameters callback that rejects bad values with a reason; `current()` gives the config
    in force (types and ranges first go through rclpy's descriptor checks)."""

    def on_set(params: list[Parameter]) -> SetParametersResult:
        try:
            merged(current(), params)
        except ParamError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        return SetParametersResult(successful=True)

    return on_set


# ----------------------------------------------------------------------------- params files and arguments
def check_params_file(path: str, node_fqn: str) -> None:
    """Check a ROS 2 params file before rcl reads it; raise ParamError with one line naming the problem.

    Checks the YAML syntax and the layout `<node or pattern>: {ros__parameters: {...}}`. For the entries
    that apply to `node_fqn` (e.g. '/register_node', or patterns like '/**'), every key must be a
    parameter of this node with a valid value, and the values together must be a valid config.
    """
    try:
        with open(path, encoding="utf-8") as f:
            doc = yaml.safe_load(f)
    except OSError as exc:
        raise ParamError(f"params file {path}: cannot read it ({exc.strerror})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise ParamError(f"params file {path}: invalid YAML{where}: {getattr(exc, 'problem', exc)}") from None
    if not isinstance(doc, dict) or not doc:
        raise ParamError(f"params file {path}: expected a mapping '<node name>: {{ros__parameters: ...}}'")
    values: dict[str, Any] = {}
    for key, entry in doc.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("ros__parameters"), dict):
            raise ParamError(f"params file {path}: entry '{key}' needs a 'ros__parameters' mapping")
        if not fnmatch.fnmatchcase(node_fqn, "/" + str(key).lstrip("/")):
            continue
        for name, value in _flatten(entry["ros__parameters"]):
            if any(fnmatch.fnmatchcase(name, b) for b in BUILTIN):
                continue
            if name not in BY_NAME:
                raise ParamError(f"params file {path}: {unknown_text(name)}")
            values[name] = value
    build(values, f"params file {path}: ")


def ros_arguments(argv: list[str]) -> Iterator[tuple[str, str]]:
    """(flag, value) of the two-token arguments inside --ros-args sections: --params-file, -r/--remap, -p."""
    in_ros = False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            in_ros = True
        elif arg == "--":
            in_ros = False
        elif in_ros and arg in ("--params-file", "-r", "--remap", "-p", "--param") and i + 1 < len(argv):
            yield arg, argv[i + 1]


def params_files(argv: list[str]) -> list[str]:
    """The --params-file arguments of `argv`."""
    return [value for flag, value in ros_arguments(argv) if flag == "--params-file"]


def node_fqn(argv: list[str], name: str) -> str:
    """The fully qualified name of node `name` after `-r __ns:=` / `-r __node:=` in argv (rcl uses the first
    of each). rclpy offers no way to ask before rclpy.init, which already reads the params files."""
    remaps = [value for flag, value in ros_arguments(argv) if flag in ("-r", "--remap")]
    ns = next((r.split(":=", 1)[1] for r in remaps if r.startswith("__ns:=")), "")
    name = next((r.split(":=", 1)[1] for r in remaps if r.startswith("__node:=")), name)
    return f"/{ns.strip('/')}/{name}" if ns.strip("/") else f"/{name}"


def _flatten(mapping: dict, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        out += _flatten(value, name + ".") if isinstance(value, dict) else [(name, value)]
    return out


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
