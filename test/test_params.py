"""register_node's parameters are derived from the config dataclasses; config/genreg.yaml (scenes),
config/genreg_map.yaml (map mode) and config/genreg_objects.yaml (objects) are generated from them."""

from __future__ import annotations

import dataclasses
import re
import subprocess
import sys
import typing
from pathlib import Path

import numpy as np
import pytest
import yaml

from genreg_core.config import (
    SCENE_REGISTRATION,
    LocalizationConfig,
    PDSACConfig,
    RefineConfig,
    RegistrationConfig,
    settings,
)
from genreg_core.errors import ConfigError
from genreg_core.preprocess import PreprocessConfig
from genreg_ros import config, params
from genreg_ros.config import (
    PROFILES,
    SCENE_OVERRIDES,
    SETTINGS,
    NodeConfig,
    RegistrationScalars,
    defaults,
    yaml_text,
)

CONFIG = Path(__file__).resolve().parent.parent / "config"
PARAMS_FILE = CONFIG / "genreg.yaml"


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


@pytest.mark.parametrize("name", list(PROFILES))
def test_params_files_are_the_generated_ones(name):
    assert (CONFIG / name).read_text() == yaml_text(name), (
        f"config/{name} is out of date: python -m genreg_ros.config --write")


@pytest.mark.parametrize("name", list(PROFILES))
def test_params_file_names_and_values_match_the_dataclasses(name):
    doc = yaml.safe_load((CONFIG / name).read_text())
    in_file = _flatten(doc["/**"]["ros__parameters"])
    assert in_file == {s.name: params.to_ros(s, defaults(name)[s.name]) for s in SETTINGS}
    assert all(s.help for s in SETTINGS)
    params.check_params_file(str(CONFIG / name), "/register_node")


@pytest.mark.parametrize("name", list(PROFILES))
def test_a_profiles_config_is_its_params_file_read_as_the_node_reads_it(name):
    """`config.profile_config` (what harnesses run with) against the YAML file parsed and converted by the node's
    own `params.to_config`."""
    doc = yaml.safe_load((CONFIG / name).read_text())
    assert config.profile_config(name) == params.to_config(_flatten(doc["/**"]["ros__parameters"]))


def test_scene_file_is_for_the_scene_model_and_objects_file_for_the_object_model():
    assert defaults("genreg.yaml")["model.checkpoint"] == SCENE_OVERRIDES["model.checkpoint"] == "7scenes"
    assert defaults("genreg_objects.yaml")["model.checkpoint"] == NodeConfig().model.checkpoint == "modelnet40_dgcnn"


def test_map_file_is_the_scene_file_in_map_mode_with_a_latched_map_and_a_sensor_data_camera():
    scene, mapped = defaults("genreg.yaml"), defaults("genreg_map.yaml")
    differ = {k for k in scene if scene[k] != mapped[k]}
    assert differ == {"workers", "map.enabled", "qos.target_reliability", "qos.target_durability", "budget.latency"}
    assert mapped["budget.latency"] == 0.0  # the latency budget is not used in map mode
    assert mapped["map.enabled"] and mapped["workers"] == 1
    # the map latched (reliable + transient_local), the camera best effort (accepts SensorDataQoS publishers)
    assert (mapped["qos.target_reliability"], mapped["qos.target_durability"]) == ("reliable", "transient_local")
    assert mapped["qos.reliability"] == "best_effort"
    assert NodeConfig().qos.target_reliability == "same" and not NodeConfig().map.enabled


def test_generating_the_params_files_needs_no_rclpy():
    code = ("import sys, genreg_ros.config as c\n"
            "texts = [c.yaml_text(name) for name in c.PROFILES]\n"
            "assert c.main(['--check']) == 0 and all('ros__parameters' in t for t in texts)\n"
            "loaded = sorted(m for m in sys.modules if m.split('.')[0] == 'rclpy' or m == 'genreg_ros.params')\n"
            "assert not loaded, loaded\n")
    run = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True,
                         cwd=CONFIG.parent, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]


def test_the_documented_commands_are_the_real_ones():
    documented = re.findall(r"python -m genreg_ros\.config([^\n#]*)", config.__doc__)
    assert documented and {tuple(args.split()) for args in documented} == {("--write",), ("--check",)}
    assert config.main(["--check"]) == 0
    with pytest.raises(SystemExit):
        config.main(["--check", "config/genreg.yaml"])  # what it once said: argparse rejects it


def test_scene_file_registers_with_the_cores_scene_preset():
    scene = params.to_config({name: params.to_ros(params.BY_NAME[name], v) for name, v in defaults("genreg.yaml").items()})
    assert scene.registration_config() == SCENE_REGISTRATION
    assert scene.model.checkpoint == "7scenes" and scene.workers == 2
    assert set(SCENE_OVERRIDES) == {"model.checkpoint", "workers", "refine.method", "refine.fine_fraction",
                                    "pdsac.sample_size", "registration.passes", "budget.latency"}


def test_registration_scalars_are_the_cores_scalar_settings():
    core_types, my_types = typing.get_type_hints(RegistrationConfig), typing.get_type_hints(RegistrationScalars)
    core = {f.name: f for f in dataclasses.fields(RegistrationConfig) if not dataclasses.is_dataclass(core_types[f.name])}
    mine = {f.name: f for f in dataclasses.fields(RegistrationScalars)}
    assert mine.keys() == core.keys()
    for name, f in mine.items():
        assert (f.default, f.metadata, my_types[name]) == (core[name].default, core[name].metadata, core_types[name])
    nested = {f.name for f in dataclasses.fields(RegistrationConfig)} - core.keys()
    assert nested == {"pdsac", "refine", "fallback"}  # NodeConfig's groups of the same names
    c = NodeConfig(registration=RegistrationScalars(min_points=40, seed=None, estimate_threads=2))
    assert c.registration_config() == RegistrationConfig(refine=c.refine, min_points=40, seed=None, estimate_threads=2)
    with pytest.raises(ConfigError, match="registration.min_points"):
        RegistrationScalars(min_points=1)


def test_a_16_value_initial_guess_must_be_rigid():
    T = [0.0, -1.0, 0.0, 1.0, 1.0, 0.0, 0.0, 2.0, 0.0, 0.0, 1.0, 3.0, 0.0, 0.0, 0.0, 1.0]
    assert NodeConfig(initial_guess=tuple(T)).initial_guess_matrix()[:3, 3].tolist() == [1.0, 2.0, 3.0]
    for bad, text in ((T[:15] + [2.0], "last row"), ([2 * v for v in T[:12]] + T[12:], "rigid"),
                      ([-v for v in T[:12]] + T[12:], "det")):
        with pytest.raises(ConfigError, match=text):
            NodeConfig(initial_guess=tuple(bad))


def test_base_T_source_is_the_sensors_mounting():
    """[x, y, z, qx, qy, qz, qw] and the 16-value form give the same T_base_source (scipy's quaternion)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_euler("ZYX", [0.3, 0.2, -0.1]).as_quat()
    c = NodeConfig(base_frame="base_link", base_T_source=(0.4, 0.1, 1.8, *q))
    T = c.base_T_source_matrix()
    np.testing.assert_allclose(T[:3, :3], Rotation.from_quat(q).as_matrix(), atol=1e-12)
    assert T[:3, 3].tolist() == [0.4, 0.1, 1.8] and NodeConfig().base_T_source_matrix() is None
    np.testing.assert_allclose(NodeConfig(base_frame="b", base_T_source=tuple(T.ravel())).base_T_source_matrix(), T)


def test_distance_settings_are_metres_with_auto():
    for name in ("pdsac.inlier_threshold", "refine.max_correspondence_distance", "refine.guard_distance"):
        s = params.BY_NAME[name]
        assert s.default == 0.0 and "auto" in s.help and re.search(r"\bm\b", s.help), (name, s.help)


def test_unknown_parameter_text_suggests_the_nearest():
    assert params.unknown_text("model.checkpont") == (
        "unknown parameter 'model.checkpont' (did you mean model.checkpoint?)")
    assert params.unknown_text("bogus") == "unknown parameter 'bogus'"


def test_empty_arrays_of_any_type_become_double_arrays():
    from rclpy.parameter import Parameter

    (p,) = params.coerce_arrays([Parameter("initial_guess", Parameter.Type.BOOL_ARRAY, [])])
    assert p.type_ == Parameter.Type.DOUBLE_ARRAY and p.value == []
    (p,) = params.coerce_arrays([Parameter("preprocess.crop_max", Parameter.Type.INTEGER_ARRAY, [1, 2, 3])])
    assert p.type_ == Parameter.Type.DOUBLE_ARRAY and list(p.value) == [1.0, 2.0, 3.0]


def test_node_defaults_are_the_core_defaults_except_refinement():
    c = NodeConfig()
    assert c.pdsac == PDSACConfig() and c.preprocess == PreprocessConfig()
    assert c.refine == dataclasses.replace(RefineConfig(), method="point_to_point", max_iterations=20)
    assert RefineConfig().method == "none" and RefineConfig().max_iterations == 10  # the API's default
    core = {s.name: s.default for s in settings(RegistrationConfig)}
    node = {s.name.removeprefix("registration."): s.default for s in SETTINGS if s.name.startswith("registration.")}
    assert node == {k: v for k, v in core.items() if "." not in k}
    assert c.registration_config() == RegistrationConfig(refine=c.refine)


def test_ros_values_map_back_to_the_core_configs():
    values = {"registration.seed": -1, "preprocess.crop_min": [], "preprocess.crop_max": [],
              "pdsac.num_hypotheses": 64, "refine.method": "point_to_plane", "registration.device": "cpu"}
    c = params.to_config(values)
    r = c.registration_config()
    assert r.seed is None and r.pdsac.num_hypotheses == 64 and r.refine.method == "point_to_plane"
    assert r.refine.max_iterations == 20 and c.preprocess.crop_min is None
    c = params.to_config({"preprocess.crop_min": [0.0, 0.0, 0.0], "preprocess.crop_max": [1, 2, 3],
                          "registration.seed": 7})
    assert c.preprocess.crop_max == (1.0, 2.0, 3.0) and c.registration_config().seed == 7
    assert params.ros_values(c)["preprocess.crop_max"] == [1.0, 2.0, 3.0]
    assert params.ros_values(NodeConfig())["registration.seed"] == 0


@pytest.mark.parametrize(("values", "text"), [
    ({"refine.method": "bogus"}, "refine.method must be one of"),
    ({"preprocess.min_range": 5.0, "preprocess.max_range": 1.0}, "min_range"),
    ({"preprocess.crop_min": [1.0, 1.0, 1.0]}, "crop_min and crop_max"),
    ({"initial_guess": [0.0] * 5}, "initial_guess must have 0, 7 or 16 values"),
    ({"initial_guess": [0.0] * 7}, "quaternion"),
    ({"registration.device": "gpu"}, "device"),
    ({"base_frame": "base_link"}, "base_frame and base_T_source go together"),
    ({"base_T_source": [0.0, 0.0, 1.8, 0.0, 0.0, 0.0, 1.0]}, "base_frame and base_T_source go together"),
    ({"base_frame": "base_link", "base_T_source": [0.0] * 7}, "base_T_source quaternion"),
    ({"base_frame": "base_link", "base_T_source": [1.0] * 16}, "base_T_source"),
])
def test_invalid_values_are_named(values, text):
    with pytest.raises(ConfigError, match=text):
        params.to_config(values)


def test_descriptors_carry_ranges_and_read_only():
    d = params.descriptor(params.BY_NAME["sync.queue_size"])
    assert (d.integer_range[0].from_value, d.integer_range[0].to_value) == (1, 100) and not d.read_only
    assert params.descriptor(params.BY_NAME["model.checkpoint"]).read_only
    assert params.descriptor(params.BY_NAME["registration.seed"]).integer_range[0].from_value == -1
    assert "point_to_plane" in params.descriptor(params.BY_NAME["refine.method"]).description


@pytest.mark.parametrize(("content", "text"), [
    ("/**:\n  ros__parameters:\n    registration:\n      pases: 2\n", "unknown parameter 'registration.pases'"),
    ("/**:\n  ros__parameters:\n    model:\n      device: cpu\n", "did you mean registration.device?"),
    ("/**:\n  ros__parameters:\n    sync:\n      slop: 1\n", "sync.slop must be a double (write 1.0, not 1)"),
    ("/**:\n  ros__parameters:\n    preprocess: {min_range: 2.0, max_range: 1.0}\n", "min_range"),
    ("/**:\n  ros__parameters:\n    sync:\n      time_jump: 1.0\n",  # a removed parameter says what replaced it
     "unknown parameter 'sync.time_jump' (removed: a stamp more than sync.slop older"),
    ("/**:\n  ros__parameters:\n    target_crop_radius: 4.0\n",  # one way to localise in a map: map mode
     "unknown parameter 'target_crop_radius' (removed: use map.enabled"),
    ("/other_node:\n  ros__parameters:\n    bogus: 1\n", None),  # another node's entry is not checked
])
def test_params_file_check(tmp_path, content, text):
    path = tmp_path / "p.yaml"
    path.write_text(content)
    if text is None:
        params.check_params_file(str(path), "/register_node")
        return
    with pytest.raises(params.ParamError, match=text.replace("(", r"\(").replace(")", r"\)").replace("?", r"\?")):
        params.check_params_file(str(path), "/register_node")
    params.check_params_file(str(PARAMS_FILE), "/register_node")


def test_node_name_from_arguments():
    argv = ["node", "--ros-args", "-r", "__ns:=/a/b", "-r", "__ns:=/c", "-r", "__node:=n", "--params-file", "f.yaml"]
    assert params.node_fqn(argv, "register_node") == "/a/b/n"  # rcl takes the first __ns
    assert params.node_fqn(["node"], "register_node") == "/register_node"
    assert params.params_files(argv) == ["f.yaml"] and params.params_files(["node", "--params-file", "x"]) == []



def test_every_map_localisation_setting_is_a_start_up_parameter_with_the_cores_default_range_and_help(tmp_path):
    core = {s.name: s for s in settings(LocalizationConfig)}
    mine = {s.name.removeprefix("map.localization."): s for s in SETTINGS if s.name.startswith("map.localization.")}
    assert mine.keys() == core.keys() and len(core) == len(dataclasses.fields(LocalizationConfig))
    for name, s in mine.items():
        c = core[name]
        assert (s.default, s.type, s.help, s.low, s.high) == (c.default, c.type, c.help, c.low, c.high), name
        assert s.start_up and s.low is not None and s.high is not None, name  # read once; every one has a range
    assert NodeConfig().map.localization == LocalizationConfig()
    assert params.descriptor(params.BY_NAME["map.localization.candidates"]).read_only
    path = tmp_path / "p.yaml"  # one threshold per meaning: a miss is a scan whose pose is not published
    path.write_text("/**:\n  ros__parameters:\n    map:\n      lost_confidence: 0.5\n")
    with pytest.raises(params.ParamError, match=r"'map.lost_confidence' \(removed: a scan is a miss when its pose"):
        params.check_params_file(str(path), "/register_node")


@pytest.fixture
def rcl_context():
    import rclpy

    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    yield ctx
    rclpy.shutdown(context=ctx)


def _declared(ctx, **overrides) -> NodeConfig:
    """The NodeConfig `params.declare` gives a node started with these parameters (dots written as __)."""
    from rclpy.node import Node
    from rclpy.parameter import Parameter

    node = Node("genreg_params_test", context=ctx, parameter_overrides=[
        Parameter(k.replace("__", "."), value=v) for k, v in overrides.items()])
    try:
        return params.declare(node)
    finally:
        node.destroy_node()


def test_a_map_setting_given_as_a_ros_parameter_reaches_the_map_localizer(rcl_context, untrained_checkpoint):
    from genreg_core.localization import MapLocalizer
    from genreg_core.registration import Registrar

    c = _declared(rcl_context, map__enabled=True, map__localization__voxel_size=0.05,
                  map__localization__candidates=5, map__localization__track_below=0.7)
    assert c.map.localization == LocalizationConfig(voxel_size=0.05, candidates=5, track_below=0.7)
    points = np.random.default_rng(0).uniform(0.0, 2.0, (2000, 3))
    # what the node builds in map mode (genreg_ros.node: MapLocalizer(..., config=c.map.localization))
    loc = MapLocalizer(points, registrar=Registrar.from_checkpoint(str(untrained_checkpoint), c.registration_config()),
                       config=c.map.localization)
    assert loc.config.candidates == 5 and loc.config.track_below == 0.7 and loc.voxel_size == 0.05
    assert params.ros_values(c)["map.localization.candidates"] == 5


@pytest.mark.parametrize(("overrides", "text"), [
    ({"map__localization__place_spacing": 50.0}, "map.localization.place_spacing"),
    ({"map__localization__candidates": 0}, "map.localization.candidates"),
    ({"map__localization__local_keep": 4.0}, "localization.local_keep (4.0) must be below localization.local_radius"),
    ({"map__enabled": True, "map__localization__place_points": 40, "registration__min_points": 64},
     "map.localization.place_points (40) must be at least registration.min_points (64)"),
])
def test_out_of_range_map_settings_are_refused_with_one_line(rcl_context, overrides, text):
    with pytest.raises(params.ParamError, match=re.escape(text)) as error:
        _declared(rcl_context, **overrides)
    assert "\n" not in str(error.value), str(error.value)
