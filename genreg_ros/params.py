"""Every ROS parameter of register_node: one table of specs, declaration, validation, params-file check.

Units: metres (REP-103) and seconds, except the PDSAC/ICP distances, which are in the core's unit-box
units (fractions of the source cloud's bounding-box size, see genreg_core.geometry.normalize_pair).
Empty arrays and empty strings mean "off" / "take it from the message".
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
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
from scipy.spatial.transform import Rotation

from genreg_core.config import PDSACConfig, RefineConfig, RegistrationConfig
from genreg_ros.sync import MODES

DOUBLE_ARRAY = "double_array"
_TYPES = {
    bool: (ParameterType.PARAMETER_BOOL, "bool"),
    int: (ParameterType.PARAMETER_INTEGER, "integer"),
    float: (ParameterType.PARAMETER_DOUBLE, "double"),
    str: (ParameterType.PARAMETER_STRING, "string"),
    DOUBLE_ARRAY: (ParameterType.PARAMETER_DOUBLE_ARRAY, "list of doubles"),
}
# Parameters rclpy itself handles, allowed in params files.
_BUILTIN = ("use_sim_time", "start_type_description_service", "qos_overrides.*")


@dataclass(frozen=True)
class Spec:
    """One parameter: name, default, type, meaning, limits. Ranges are inclusive."""

    name: str
    default: Any
    description: str
    type: Any = None  # bool, int, float, str or DOUBLE_ARRAY; None: type(default)
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    lengths: tuple[int, ...] | None = None  # allowed lengths of an array
    read_only: bool = False  # fixed after start-up (needs a restart)

    @property
    def kind(self) -> Any:
        return self.type if self.type is not None else type(self.default)


# Registration defaults come from the core's config (one place); the node's own choices are written here:
# it refines with ICP by default (the core's default is no refinement) and runs more ICP iterations.
_PDSAC, _REFINE, _REG = PDSACConfig(), RefineConfig(), RegistrationConfig()

SPECS: tuple[Spec, ...] = (
    Spec("model.checkpoint", "modelnet40", "Shipped model name (modelnet40, 7scenes) or a .pt checkpoint path.",
         read_only=True),
    Spec("model.device", "cpu", "Torch device: cpu, cuda or cuda:<index>.", read_only=True),
    Spec("model.num_points", 0, "Expected model N (points per cloud fed to the network); 0 accepts the "
         "checkpoint's N.", low=0, high=65536, read_only=True),
    Spec("model.num_threads", 0, "Torch CPU threads; 0 keeps torch's default.", low=0, high=256, read_only=True),
    Spec("pdsac.num_hypotheses", _PDSAC.num_hypotheses, "PDSAC hypotheses m drawn per registration.", low=1, high=100000),
    Spec("pdsac.sample_size", _PDSAC.sample_size, "PDSAC correspondences k per minimal set.", low=3, high=64),
    Spec("pdsac.inlier_threshold", _PDSAC.inlier_threshold, "PDSAC inlier residual, unit-box units.", low=1e-6, high=1.0),
    Spec("refine.method", "point_to_point", "ICP refinement after PDSAC.",
         choices=("none", "point_to_point", "point_to_plane")),
    Spec("refine.max_iterations", 20, "ICP iterations.", low=1, high=1000),
    Spec("refine.max_correspondence_distance", _REFINE.max_correspondence_distance, "ICP correspondence distance, unit-box units.",
         low=1e-6, high=1.0),
    Spec("refine.num_points", _REFINE.num_points, "Points per cloud used by ICP and the fitness measure.", low=16,
         high=1_000_000),
    Spec("refine.guard_below", _REFINE.guard_below, "Below this confidence ICP also runs from the initial guess; "
         "the better-overlapping start wins (0: off).", low=0.0, high=1.0),
    Spec("refine.guard_distance", _REFINE.guard_distance, "ICP correspondence distance from the initial guess, "
         "unit-box units.", low=1e-6, high=10.0),
    Spec("refine.guard_iterations", _REFINE.guard_iterations, "ICP iterations from the initial guess.", low=1, high=1000),
    Spec("registration.passes", _REG.passes, "Network + PDSAC passes; each registers the residual of the previous.",
         low=1, high=10),
    Spec("registration.min_points", _REG.min_points, "Clouds with fewer finite points (after preprocessing) fail.", low=4,
         high=1_000_000),
    Spec("registration.seed", 0, "Random seed of subsampling and PDSAC; -1 draws fresh randomness each time.",
         low=-1, high=2**31 - 1),
    Spec("preprocess.min_range", 0.0, "Drop points closer than this to the sensor origin, m (0: off).",
         low=0.0, high=1e4),
    Spec("preprocess.max_range", 0.0, "Drop points farther than this from the sensor origin, m (0: off).",
         low=0.0, high=1e4),
    Spec("preprocess.voxel_size", 0.0, "Voxel-grid downsampling edge, m (0: off).", low=0.0, high=100.0),
    Spec("preprocess.crop_min", [], "Crop box minimum corner [x, y, z] in the cloud's frame, m ([]: off).",
         type=DOUBLE_ARRAY, lengths=(0, 3)),
    Spec("preprocess.crop_max", [], "Crop box maximum corner [x, y, z], m ([]: off).", type=DOUBLE_ARRAY,
         lengths=(0, 3)),
    Spec("sync.mode", "approximate", "approximate: pair by stamp within slop; latest_target: each source "
         "against the newest target.", choices=MODES),
    Spec("sync.slop", 0.05, "Largest stamp difference of a pair, s.", low=0.0, high=10.0),
    Spec("sync.queue_size", 5, "Unpaired messages kept per topic.", low=1, high=100),
    Spec("qos.reliability", "best_effort", "Subscription reliability: best_effort (sensor data, accepts "
         "both kinds of publisher) or reliable.", choices=("best_effort", "reliable"), read_only=True),
    Spec("qos.depth", 5, "Subscription history depth.", low=1, high=100, read_only=True),
    Spec("qos.publisher_reliability", "reliable", "Reliability of the output topics.",
         choices=("best_effort", "reliable"), read_only=True),
    Spec("source_frame", "", "Source frame id; empty: the source header's frame_id.", ),
    Spec("target_frame", "", "Target frame id; empty: the target header's frame_id."),
    Spec("max_points", 1_000_000, "Clouds with more points (width * height) are dropped.", low=1,
         high=100_000_000),
    Spec("initial_guess", [], "target_from_source start: [] none, [x, y, z, qx, qy, qz, qw] (m) or 16 "
         "row-major 4x4 values. The initial_guess topic overrides it.", type=DOUBLE_ARRAY,
         lengths=(0, 7, 16)),
    Spec("use_last_result_as_guess", False, "Start each registration from the previous result (tracking)."),
    Spec("min_fitness", 0.0, "Results with lower fitness are counted as failed and not published.",
         low=0.0, high=1.0),
    Spec("warn_confidence", 0.3, "Results with lower confidence are published, with a throttled warning, a "
         "low_confidence count and a WARN diagnostics status.", low=0.0, high=1.0),
    Spec("publish_generated", False, "Also publish the generated source cloud (debugging)."),
    Spec("publish_tf", False, "Broadcast the transform on /tf (needs tf2_ros).", read_only=True),
    Spec("diagnostics.period", 1.0, "Diagnostics publishing period, s.", low=0.05, high=60.0, read_only=True),
    Spec("diagnostics.stale_timeout", 2.0, "Warn when a cloud topic is silent this long, s.", low=0.1,
         high=3600.0),
)
BY_NAME = {s.name: s for s in SPECS}


class ParamError(ValueError):
    """A parameter value or a params file is invalid; the message is one line."""


def check_value(spec: Spec, value: Any) -> str | None:
    """Why `value` is invalid for `spec`, or None. Checks type, range, choices and array length."""
    kind = spec.kind
    if kind is DOUBLE_ARRAY:
        if value is None:
            value = []
        if not isinstance(value, (list, tuple)) or not all(
            isinstance(v, float) or (isinstance(v, int) and not isinstance(v, bool)) for v in value
        ):
            return f"{spec.name} must be a list of numbers"
        if not all(math.isfinite(v) for v in value):
            return f"{spec.name} must hold finite numbers"
        if spec.lengths is not None and len(value) not in spec.lengths:
            return f"{spec.name} must have {' or '.join(map(str, spec.lengths))} values, got {len(value)}"
        return None
    ok = isinstance(value, kind) and (kind is bool or not isinstance(value, bool))
    if not ok:
        hint = " (write 1.0, not 1)" if kind is float and isinstance(value, int) else ""
        return f"{spec.name} must be a {_TYPES[kind][1]}{hint}, got {value!r}"
    if spec.choices is not None and value not in spec.choices:
        return f"{spec.name} must be one of {list(spec.choices)}, got {value!r}"
    if kind in (int, float):
        if not math.isfinite(value):
            return f"{spec.name} must be finite"
        if (spec.low is not None and value < spec.low) or (spec.high is not None and value > spec.high):
            return f"{spec.name} must be in [{spec.low}, {spec.high}], got {value!r}"
    if spec.name == "model.device" and not (value == "cpu" or value == "cuda" or (
        value.startswith("cuda:") and value[5:].isdigit()
    )):
        return f"model.device must be cpu, cuda or cuda:<index>, got {value!r}"
    return None


def check_all(values: dict[str, Any]) -> str | None:
    """Cross-parameter checks on a complete set of values; the reason or None."""
    lo, hi = values["preprocess.min_range"], values["preprocess.max_range"]
    if hi > 0 and lo >= hi:
        return f"preprocess.min_range ({lo}) must be < preprocess.max_range ({hi})"
    cmin, cmax = list(values["preprocess.crop_min"] or []), list(values["preprocess.crop_max"] or [])
    if len(cmin) != len(cmax):
        return "preprocess.crop_min and preprocess.crop_max must both be empty or both have 3 values"
    if cmin and not all(a < b for a, b in zip(cmin, cmax)):
        return f"preprocess.crop_min {cmin} must be below preprocess.crop_max {cmax} on every axis"
    try:
        guess_matrix(values["initial_guess"])
    except ParamError as exc:
        return str(exc)
    return None


def guess_matrix(values: list[float] | None) -> np.ndarray | None:
    """The initial_guess parameter as a 4x4 target_from_source matrix (None if empty).

    7 values: x, y, z (m) and a quaternion qx, qy, qz, qw (normalised here); 16 values: a row-major
    4x4 rigid transform. ParamError if the values do not describe a rigid transform.
    """
    v = np.asarray(list(values or []), dtype=np.float64)
    if v.size == 0:
        return None
    if v.size == 7:
        q = v[3:]
        if np.linalg.norm(q) < 1e-6:
            raise ParamError("initial_guess quaternion (qx, qy, qz, qw) must not be zero")
        T = np.eye(4)
        T[:3, :3] = Rotation.from_quat(q / np.linalg.norm(q)).as_matrix()
        T[:3, 3] = v[:3]
        return T
    if v.size == 16:
        T = v.reshape(4, 4)
        R = T[:3, :3]
        if not np.allclose(T[3], [0, 0, 0, 1]) or not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or (
            np.linalg.det(R) < 0
        ):
            raise ParamError("initial_guess must be a rigid transform (orthonormal R, det +1, last row 0 0 0 1)")
        return T
    raise ParamError(f"initial_guess must have 0, 7 or 16 values, got {v.size}")


def _descriptor(spec: Spec) -> ParameterDescriptor:
    extra = f" One of: {', '.join(spec.choices)}." if spec.choices else ""
    d = ParameterDescriptor(
        name=spec.name,
        type=_TYPES[spec.kind][0],
        description=spec.description + extra,
        read_only=spec.read_only,
    )
    if spec.kind is int and spec.low is not None:
        d.integer_range = [IntegerRange(from_value=int(spec.low), to_value=int(spec.high), step=0)]
    elif spec.kind is float and spec.low is not None:
        d.floating_point_range = [FloatingPointRange(from_value=float(spec.low), to_value=float(spec.high))]
    if spec.lengths:
        d.additional_constraints = f"length in {list(spec.lengths)}"
    return d


def declare(node: Node) -> dict[str, Any]:
    """Declare every parameter on `node` and return their values; ParamError on a bad value."""
    values: dict[str, Any] = {}
    for spec in SPECS:
        try:
            if spec.kind is DOUBLE_ARRAY:
                param = node.declare_parameter(spec.name, Parameter.Type.DOUBLE_ARRAY, _descriptor(spec))
                if param.value is None:  # rcl reads `[]` in YAML as "not set"
                    node.set_parameters([Parameter(spec.name, Parameter.Type.DOUBLE_ARRAY, [])])
                value = list(node.get_parameter(spec.name).value or [])
            else:
                value = node.declare_parameter(spec.name, spec.default, _descriptor(spec)).value
        except ParameterException as exc:  # rclpy's type/range errors: turn them into one line
            raise ParamError(f"parameter {spec.name}: {_one_line(exc)}") from None
        reason = check_value(spec, value)
        if reason:
            raise ParamError(reason)
        values[spec.name] = value
    reason = check_all(values)
    if reason:
        raise ParamError(reason)
    return values


def make_validator(current: Callable[[], dict[str, Any]]):
    """An on-set-parameters callback that rejects bad values with a reason; `current()` gives the values
    in force (types and ranges first go through rclpy's descriptor checks)."""

    def on_set(params: list[Parameter]) -> SetParametersResult:
        merged = dict(current())
        for p in params:
            spec = BY_NAME.get(p.name)
            if spec is None:
                continue  # use_sim_time and other rclpy parameters
            value = list(p.value or []) if spec.kind is DOUBLE_ARRAY else p.value
            reason = check_value(spec, value)
            if reason:
                return SetParametersResult(successful=False, reason=reason)
            merged[p.name] = value
        reason = check_all(merged)
        return SetParametersResult(successful=reason is None, reason=reason or "")

    return on_set


def check_params_file(path: str, node_fqn: str) -> None:
    """Check a ROS 2 params file before rcl reads it; raise ParamError with one line naming the problem.

    Checks the YAML syntax and the layout `<node or pattern>: {ros__parameters: {...}}`. For the entries
    that apply to `node_fqn` (e.g. '/register_node', or patterns like '/**'), every key must be a
    parameter of this node with a valid value.
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
    for key, entry in doc.items():
        if not isinstance(entry, dict) or not isinstance(entry.get("ros__parameters"), dict):
            raise ParamError(f"params file {path}: entry '{key}' needs a 'ros__parameters' mapping")
        pattern = "/" + str(key).lstrip("/")
        if not fnmatch.fnmatchcase(node_fqn, pattern):
            continue
        for name, value in _flatten(entry["ros__parameters"]):
            if any(fnmatch.fnmatchcase(name, b) for b in _BUILTIN):
                continue
            spec = BY_NAME.get(name)
            if spec is None:
                near = [s.name for s in SPECS if s.name.split(".")[-1] == name.split(".")[-1]]
                hint = f" (did you mean {near[0]}?)" if near else ""
                raise ParamError(f"params file {path}: unknown parameter '{name}'{hint}")
            reason = check_value(spec, value)
            if reason:
                raise ParamError(f"params file {path}: {reason}")


def params_files(argv: list[str]) -> list[str]:
    """The --params-file arguments inside --ros-args sections of `argv`."""
    files, in_ros = [], False
    for i, arg in enumerate(argv):
        if arg == "--ros-args":
            in_ros = True
        elif arg == "--":
            in_ros = False
        elif in_ros and arg == "--params-file" and i + 1 < len(argv):
            files.append(argv[i + 1])
    return files


def _flatten(mapping: dict, prefix: str = "") -> list[tuple[str, Any]]:
    out = []
    for key, value in mapping.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            out += _flatten(value, name + ".")
        else:
            out.append((name, value))
    return out


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split()) or type(exc).__name__
