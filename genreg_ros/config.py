"""register_node's settings: the core's config dataclasses plus what only the node has, in one tree.

`NodeConfig` nests the core's `PDSACConfig`, `RefineConfig`, `PreprocessConfig` and, in the map group,
`LocalizationConfig` (`map.localization`; their defaults, ranges and help live in `genreg_core`), the
`RegistrationConfig` scalars (group `registration`) and the node's own groups below. A ROS parameter's
name is the setting's dotted path (`settings(NodeConfig)`), e.g. `refine.max_iterations`;
`genreg_ros.params` declares and validates them as ROS parameters (the only module that needs rclpy),
and the params files are generated from the same list:

    python -m genreg_ros.config --write     # after changing a setting: rewrites the files in config/
    python -m genreg_ros.config --check     # exit 1 if a shipped params file is out of date

Four params files are generated from the one list: `config/genreg.yaml` (depth-camera scenes: the core's
scene preset `SCENE_REGISTRATION`, the scene model and two workers: `SCENE_OVERRIDES` below),
`config/genreg_map.yaml` (map mode: the scene settings, one worker, a latched map: `MAP_OVERRIDES`),
`config/genreg_lidar_map.yaml` (map mode for LiDAR maps: the place index, `LIDAR_MAP_OVERRIDES`) and
`config/genreg_objects.yaml` (object models: the plain defaults). This module does not import rclpy: it
holds the settings, the ROS form of a setting's value (`to_ros` / `from_ros`) and the generator.

Units: metres and seconds (REP-103); distance settings that accept 0 derive it from the clouds ("auto").
Frames and transform names: `genreg_core.geometry`.
"""


from __future__ import annotations

import argparse
import dataclasses
import sys
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from genreg_core.config import (
    OBJECT_MODEL,
    SCENE_MODEL,
    SCENE_REGISTRATION,
    FallbackConfig,
    LocalizationConfig,
    PDSACConfig,
    RefineConfig,
    RegistrationConfig,
    Setting,
    check_ranges,
    from_dict,
    setting,
    settings,
)
from genreg_core.errors import ConfigError, InvalidPointCloudError
from genreg_core.preprocess import PreprocessConfig
from genreg_ros.conversions import pose_matrix
from genreg_ros.sync import MODES

RELIABILITIES = ("best_effort", "reliable")
DURABILITIES = ("volatile", "transient_local")


@dataclass(frozen=True)
class ModelParams:
    """Which network the node loads (its threads: `registration.estimate_threads`)."""

    checkpoint: str = setting(OBJECT_MODEL, "Shipped model name (modelnet40_dgcnn: objects, 7scenes: scenes, "
                              "modelnet40_partial: partially overlapping objects, modelnet40) or a .pt checkpoint "
                              "path.", start_up=True)
    num_points: int = setting(0, "Expected model N (points per cloud fed to the network); 0 accepts the "
                              "checkpoint's N.", low=0, high=65536, start_up=True)

    def __post_init__(self) -> None:
        check_ranges(self, "model.")


_CORE_FIELDS = {f.name: f for f in dataclasses.fields(RegistrationConfig)}


def _core_setting(name: str) -> Any:
    """The field of core `RegistrationConfig` setting `name`: its default, limits and help (their one home)."""
    f = _CORE_FIELDS[name]
    return dataclasses.field(default=f.default, metadata=f.metadata)


@dataclass(frozen=True)
class RegistrationScalars:
    """The scalar settings of the core's RegistrationConfig (defaults, limits and help from the core); its
    nested groups are NodeConfig's `pdsac`, `refine` and `fallback`."""

    min_points: int = _core_setting("min_points")
    seed: int | None = _core_setting("seed")
    passes: int = _core_setting("passes")
    device: str = _core_setting("device")
    estimate_threads: int = _core_setting("estimate_threads")
    slide_fit: float = _core_setting("slide_fit")
    turn_fit: float = _core_setting("turn_fit")
    see_through: float = _core_setting("see_through")

    def __post_init__(self) -> None:
        check_ranges(self, "registration.")


@dataclass(frozen=True)
class SyncParams:
    """Pairing of source and target clouds by stamp (`genreg_ros.sync`)."""

    mode: str = setting("approximate", "approximate: pair by stamp within slop; latest_target: each source "
                        "against the newest target.", choices=MODES)
    slop: float = setting(0.05, "Largest stamp difference of a pair, s. A stamp more than this older than the "
                          "newest of its topic (bag loop, simulator reset) resets pairing, tracking and topic "
                          "guesses.", low=0.0, high=10.0)
    queue_size: int = setting(5, "Unpaired messages kept per topic.", low=1, high=100)

    def __post_init__(self) -> None:
        check_ranges(self, "sync.")


@dataclass(frozen=True)
class QosParams:
    """Quality of service of the subscriptions and the outputs. The target subscription's reliability is
    `target_reliability_resolved`: a transient_local target subscription is always reliable, since only a
    reliable subscription receives what a latched publisher sent before it existed."""

    reliability: str = setting("best_effort", "Reliability of the source subscription (and of a volatile "
                               "target's with target_reliability same): best_effort (sensor data, accepts both "
                               "kinds of publisher) or reliable.", choices=RELIABILITIES, start_up=True)
    depth: int = setting(5, "Subscription history depth.", low=1, high=100, start_up=True)
    publisher_reliability: str = setting("reliable", "Reliability of the output topics.", choices=RELIABILITIES,
                                         start_up=True)
    target_durability: str = setting("volatile", "Durability of the target subscription: transient_local "
                                     "receives a latched map published before the node started (a reliable, "
                                     "transient_local publisher) and makes the subscription reliable.",
                                     choices=DURABILITIES, start_up=True)
    target_reliability: str = setting("same", "Reliability of the target subscription: same (reliable with "
                                      "target_durability transient_local, else as reliability), best_effort or "
                                      "reliable. best_effort with transient_local is refused (it would never "
                                      "receive a latched map).", choices=("same", *RELIABILITIES), start_up=True)

    def __post_init__(self) -> None:
        check_ranges(self, "qos.")
        if self.target_durability == "transient_local" and self.target_reliability == "best_effort":
            raise ConfigError("qos.target_reliability best_effort cannot receive a latched target: with "
                              "qos.target_durability transient_local use reliable or same")

    @property
    def target_reliability_resolved(self) -> str:
        """The target subscription's reliability: target_reliability; for same, reliable with transient_local
        durability, else the source's `reliability`."""
        if self.target_reliability != "same":
            return self.target_reliability
        return "reliable" if self.target_durability == "transient_local" else self.reliability


@dataclass(frozen=True)
class MapParams:
    """Map mode: each source scan localised in a prior map (`genreg_ros.map_state`, the core's MapLocalizer).

    A scan is a hit when its pose is published (confidence at least `min_confidence`, fitness at least
    `min_fitness`) and a miss otherwise; `lost_after` misses in a row make tracking lost. The two
    thresholds of `localization` (`accept_whole`, `track_below`) only steer how hard MapLocalizer searches."""

    enabled: bool = setting(False, "Map mode: localise each source scan in the map (target_file, or the newest "
                            "target_cloud, e.g. a latched map) with MapLocalizer: without a guess on the first "
                            "scan, after ~/relocalize and when tracking is lost; otherwise from the last "
                            "accepted pose. The map is not preprocessed; needs workers 1.", start_up=True)
    lost_after: int = setting(2, "Tracking is lost after this many misses in a row (a miss: a scan whose pose is "
                              "not published, e.g. its confidence is below min_confidence): the next scan is "
                              "localised without a guess (registration_status localization: lost).",
                              low=1, high=1000)
    relocalize_confidence: float = setting(0.0, "While no pose is known (states global and lost), a pose not "
                                           "within tracking's reach of the last accepted one is published only at "
                                           "this confidence or more, besides min_confidence: every such scan is "
                                           "searched again, and a look-alike place found at a near tie would be "
                                           "tracked on (0: min_confidence alone; the LiDAR map profile: 0.8).",
                                           low=0.0, high=1.0)
    predict_motion: bool = setting(False, "Tracking starts each scan from the last accepted pose moved on at the "
                                   "velocity of the last two (constant velocity, scaled to the scans' stamps, at "
                                   "most 5 of their intervals ahead; the LiDAR map profile: on); the scan after a "
                                   "pose placed by a search (jumped) is placed again without a guess, and the two "
                                   "give the velocity; false: from the last accepted pose.")
    odometry: bool = setting(False, "Subscribe to odom (nav_msgs/Odometry, sensor-data QoS: header.frame_id the "
                             "odometry frame, child_frame_id the localised frame, i.e. base_frame or the source "
                             "frame): tracking starts each scan from the last accepted pose moved by the odometry "
                             "between the two scans' stamps (registration_status initial_guess: odometry; before "
                             "predict_motion, and also right after a placement), and each published pose gives the "
                             "map to odometry frame transform of its stamp on odom_transform (and on /tf with "
                             "publish_tf, instead of the map to the localised frame, as REP-105 asks; see "
                             "transform_tolerance and transform_publish_period).",
                             start_up=True)
    transform_tolerance: float = setting(0.2, "With map.odometry: each map to odometry frame transform is stamped "
                                         "this long after the scan's stamp (the time until which it holds, as "
                                         "AMCL's transform_tolerance; never at or before the one published before "
                                         "it), s.", low=0.0, high=10.0, start_up=True)
    transform_publish_period: float = setting(0.2, "With map.odometry: once no map to odometry frame transform has "
                                              "been published for this long (a missed or superseded scan, a silent "
                                              "sensor), the last one is published again, stamped on by the time "
                                              "since, until a reset, s; 0: only with each published pose.",
                                              low=0.0, high=60.0, start_up=True)
    publish_map: bool = setting(True, "With target_file: publish the map as the node localises in it (the file's "
                                "points after localization.map_voxel, in target_frame) once on map_cloud, reliable "
                                "and transient local, so that RViz and subscribers that join later get it.",
                                start_up=True)
    localization: LocalizationConfig = setting(LocalizationConfig(), "MapLocalizer's settings (the core's "
                                               "defaults), read when the node starts.", start_up=True)

    def __post_init__(self) -> None:
        check_ranges(self, "map.")


@dataclass(frozen=True)
class BudgetParams:
    """The latency budget (`genreg_ros.budget`): when the node falls behind, a pair does less work."""

    latency: float = setting(0.0, "Latency budget of a pair, s (from the arrival of its later cloud to its result): "
                             "a pair whose wait plus the expected seconds of a full registration exceed it is "
                             "registered with the light settings (no PDSAC modes, no more passes, no guard ICP, "
                             "no tight refinement stage, light_points refinement points), counted as light in "
                             "/diagnostics and its registration_status; 0: off. Not used in map mode.", low=0.0, high=60.0)
    light_points: int = setting(1500, "Refinement (and verification) points of a light registration.", low=16,
                                high=1_000_000)

    def __post_init__(self) -> None:
        check_ranges(self, "budget.")


@dataclass(frozen=True)
class DiagnosticsParams:
    """The /diagnostics status."""

    period: float = setting(1.0, "Diagnostics publishing period, s.", low=0.05, high=60.0, start_up=True)
    stale_timeout: float = setting(2.0, "Warn when a cloud topic is silent this long (and once when a matched "
                                   "publisher delivers nothing this long), s.", low=0.1, high=3600.0)

    def __post_init__(self) -> None:
        check_ranges(self, "diagnostics.")


@dataclass(frozen=True)
class NodeConfig:
    """Every setting of register_node. Where the node's default differs from the API's, it says so here."""

    autostart: bool = setting(True, "Configure and activate at start (lifecycle); false: wait for the "
                              "lifecycle transitions (<node>/change_state).", start_up=True)
    model: ModelParams = setting(ModelParams(), "The network.")
    workers: int = setting(1, "Pairs registered at once, each in its own worker process with its own copy of "
                           "the model (7scenes: 0.65-0.75 GB resident each, the node 0.8 GB); 1: in the node's process. Processes, not threads: "
                           "small_gicp and Open3D hold Python's interpreter lock. More than the CPU cores "
                           "do not help.", low=1, high=64, start_up=True)
    pdsac: PDSACConfig = setting(PDSACConfig(), "PDSAC (the core's defaults).")
    # The node refines with point-to-point ICP, 20 iterations; the API's default is no refinement.
    refine: RefineConfig = setting(RefineConfig(method="point_to_point", max_iterations=20),
                                   "ICP refinement: on in the node (the API's default is method none, 10 iterations).")
    fallback: FallbackConfig = setting(FallbackConfig(), "Opt-in classical global fallback (FPFH + RANSAC) "
                                       "when the confidence stays low (the core's defaults: off).")
    registration: RegistrationScalars = setting(RegistrationScalars(), "The RegistrationConfig scalars.")
    preprocess: PreprocessConfig = setting(PreprocessConfig(), "Range, crop box and voxel grid.")
    sync: SyncParams = setting(SyncParams(), "Stamp pairing.")
    qos: QosParams = setting(QosParams(), "Quality of service.")
    map: MapParams = setting(MapParams(), "Map mode (relocalisation in a prior map).")
    budget: BudgetParams = setting(BudgetParams(), "The latency budget under load.")
    source_frame: str = setting("", "Source frame id; empty: the source header's frame_id.")
    base_frame: str = setting("", "Localise this frame (e.g. base_link, z up) instead of the source cloud's: each "
                              "source cloud, once preprocessed in its own frame, is moved into it by base_T_source, "
                              "and the transform, pose, registration_status and guesses (initial_guess, initialpose) "
                              "are this frame's (the child frame). Empty: the source cloud's frame.", start_up=True)
    base_T_source: tuple[float, ...] = setting((), "With base_frame: the source sensor's mounting on it, "
                                               "T_base_source, [x, y, z, qx, qy, qz, qw] (m) or 16 row-major 4x4 "
                                               "values (what a static transform from base_frame to the sensor's "
                                               "frame says).")
    target_frame: str = setting("", "Target frame id; empty: the target header's frame_id.")
    max_points: int = setting(1_000_000, "Clouds with more points (width * height) are dropped.", low=1,
                              high=100_000_000)
    target_file: str = setting("", "A fixed target cloud (PLY or PCD, metres) in target_frame, read at "
                               "configure; every source registers against it (the target_cloud topic is not "
                               "subscribed). Empty: the target_cloud topic.", start_up=True)
    initial_guess: tuple[float, ...] = setting((), "T_target_source start: [] none, [x, y, z, qx, qy, qz, qw] (m) "
                                               "or 16 row-major 4x4 values. The initial_guess and initialpose "
                                               "topics override it.")
    initial_guess_timeout: float = setting(5.0, "A guess from a topic is used for this long after it arrived, s; "
                                           "0: until replaced.", low=0.0, high=1e6)
    use_last_result_as_guess: bool = setting(False, "Start each registration from the previous result (tracking).")
    min_fitness: float = setting(0.0, "Results with lower fitness are counted as failed and not published.",
                                 low=0.0, high=1.0)
    # the confidence is the calibrated probability that the pose is right (RegistrationResult.confidence):
    # publish what is more likely right than wrong, and warn below 80 %
    min_confidence: float = setting(0.5, "Results whose confidence (the calibrated probability that the pose is right) "
                                    "is lower are not published (counted as failed.low_confidence_rejected; in map "
                                    "mode a miss). A checkpoint without a calibration gives an uncalibrated score: "
                                    "lower it there.", low=0.0, high=1.0)
    warn_confidence: float = setting(0.8, "Results with lower confidence are published, with a throttled "
                                     "warning, a low_confidence count and a WARN diagnostics status.",
                                     low=0.0, high=1.0)
    publish_generated: bool = setting(False, "Also publish the generated source cloud (debugging).")
    publish_tf: bool = setting(False, "Broadcast the transform on /tf (needs tf2_ros).", start_up=True)
    diagnostics: DiagnosticsParams = setting(DiagnosticsParams(), "The /diagnostics status.")

    def __post_init__(self) -> None:
        check_ranges(self)
        self.registration_config()  # the core's own checks (e.g. the device name)
        self.initial_guess_matrix()
        if bool(self.base_frame) != bool(self.base_T_source):
            raise ConfigError("base_frame and base_T_source go together: give both (the frame localised and the "
                              "source sensor's mounting on it) or neither")
        self.base_T_source_matrix()
        if self.target_file and not self.target_frame:
            raise ConfigError("target_file needs target_frame (the file has no frame id)")
        if self.map.odometry and not self.map.enabled:
            raise ConfigError("map.odometry needs map.enabled (odometry moves the pose tracked in a map)")
        if self.map.enabled and self.workers != 1:
            raise ConfigError(f"map.enabled needs workers 1 (scans are localised in the node's process), got {self.workers}")
        if self.map.enabled and self.map.localization.place_points < self.registration.min_points:
            raise ConfigError(f"map.localization.place_points ({self.map.localization.place_points}) must be at "
                              f"least registration.min_points ({self.registration.min_points})")

    def registration_config(self) -> RegistrationConfig:
        """The core's RegistrationConfig: the groups pdsac, refine and fallback, and the `registration` scalars."""
        r = self.registration
        return RegistrationConfig(pdsac=self.pdsac, refine=self.refine, fallback=self.fallback,
                                  min_points=r.min_points, seed=r.seed, passes=r.passes, device=r.device,
                                  estimate_threads=r.estimate_threads, slide_fit=r.slide_fit,
                                  turn_fit=r.turn_fit, see_through=r.see_through)

    def initial_guess_matrix(self) -> np.ndarray | None:
        """The initial_guess setting as a 4x4 T_target_source (None if empty); ConfigError if not rigid."""
        return transform_setting(self.initial_guess, "initial_guess")

    def base_T_source_matrix(self) -> np.ndarray | None:
        """The base_T_source setting as a 4x4 T_base_source (None if empty: no base_frame); ConfigError if not
        rigid."""
        return transform_setting(self.base_T_source, "base_T_source")


def transform_setting(values: tuple[float, ...], name: str) -> np.ndarray | None:
    """A transform setting's 4x4 (None if empty): [x, y, z, qx, qy, qz, qw] or 16 row-major values;
    ConfigError, naming the setting, if it is neither or not rigid."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return None
    if v.size == 7:
        try:
            return pose_matrix(v[:3], v[3:])
        except ValueError:
            raise ConfigError(f"{name} quaternion (qx, qy, qz, qw) must not be zero") from None
    if v.size == 16:
        from genreg_core.prepare import check_transform  # the core's check (imports torch: only here)

        T = v.reshape(4, 4)
        try:
            check_transform(T, name)
        except InvalidPointCloudError as exc:
            raise ConfigError(str(exc)) from None
        if not np.allclose(T[3], [0, 0, 0, 1]):
            raise ConfigError(f"{name} must be a rigid transform (last row 0 0 0 1)")
        return T
    raise ConfigError(f"{name} must have 0, 7 or 16 values, got {v.size}")


def registration_overrides(config: RegistrationConfig) -> dict[str, Any]:
    """The settings (parameter name -> value) in which a NodeConfig registering with `config` differs from
    NodeConfig's defaults."""
    scalars = RegistrationScalars(**{f.name: getattr(config, f.name) for f in dataclasses.fields(RegistrationScalars)})
    node = NodeConfig(pdsac=config.pdsac, refine=config.refine, fallback=config.fallback, registration=scalars)
    base = {s.name: s.default for s in settings(NodeConfig())}
    return {s.name: s.default for s in settings(node) if s.default != base[s.name]}

SETTINGS: tuple[Setting, ...] = settings(NodeConfig)


# ----------------------------------------------------------------------------- the params files
CONFIG_DIR = Path(__file__).resolve().parent.parent / "config"
# The shipped params files: name -> (what it is for, the settings that differ from NodeConfig's defaults).
# Scenes: the scene model and the core's scene preset (genreg_core.config.SCENE_REGISTRATION: small_gicp's
# GICP and the scene PDSAC settings, MODEL_CARD.md); two workers: a 30 Hz depth camera's full-resolution
# pairs need both cores (scripts/bench_node.py soak)
# The scene profile streams depth frames: a 75 ms latency budget (light registrations when the node falls behind)
SCENE_OVERRIDES: dict[str, Any] = {"model.checkpoint": SCENE_MODEL, **registration_overrides(SCENE_REGISTRATION),
                                   "workers": 2, "budget.latency": 0.075}
# Spinning LiDARs, pair mode: the scene profile on scans voxelised to 0.5 m (a raw scan's points crowd the sensor: the
# network's samples were mostly its nearest rings, which fit best laid over the other scan's, so scans 9-20 m apart
# along a road came back with the sensors put together; on the training campuses' road pairs 12 m apart 19 of 20
# right against 9, 0.5 m rather than 1 m, which lost a room's scans); a pose that seats 0.85 as many points slid four
# spacings (about 1.7 m) along the scan's main axis held (slide_fit; on the training campuses, a VLP-32-like and an
# HDL-64-like sensor, 300 pairs: of street pairs 1-20 m apart turned by any yaw all 78 right ones kept and all 14
# confidently wrong ones held, slid 7-30 m or turned; consecutive drive scans 98 of 98 kept (slid two spacings, 31
# held); corridors are alike along their length: of pairs 0.5-8 m apart 47 of 52 right kept, 15 of 23 wrong held;
# counted within two spacings, not one, of 240 more corridor pairs 104 of 105 right kept and 12 -> 5 wrong); a
# confident pose that seats 0.9 as many points at a distinct pose turned 90, 180 or 270 deg about the sensor's z axis
# held (turn_fit; a corridor alike turned around: of 200 training corridor pairs 0.5-8 m apart 99 of 103 right kept, 8
# of 15 confidently wrong held, no street pose held; 5-10 ms more a confident pose); a confident pose whose scan, placed by
# it, would have seen through 0.13 or more of the other scan's structure 1 m above the ground held (see_through: a
# corridor's pose turned or slid puts walls where the scan saw through doorways; of the training campuses' confident
# poses, 496 right ones saw through at most 0.113, 5 wrong corridor ones 0.115-0.22: 4 held, every right one kept;
# about 1 ms a confident pose); no latency budget (a 10 Hz scan has 100 ms; light registrations, 1,500 points,
# accepted 65 of 96 right training street pairs against 76 in full, with the same 3 confidently wrong; two workers
# keep up with full ones at 10 Hz)
LIDAR_OVERRIDES: dict[str, Any] = {**SCENE_OVERRIDES, "preprocess.voxel_size": 0.5, "registration.slide_fit": 0.85,
                                   "registration.turn_fit": 0.9, "registration.see_through": 0.13,
                                   "budget.latency": 0.0}
# Map mode: the scene profile localising scans in a prior map, in the node's process (workers 1); the map
# latched (reliable, transient_local), the camera best effort (SensorDataQoS)
MAP_OVERRIDES: dict[str, Any] = {**SCENE_OVERRIDES, "workers": 1, "map.enabled": True, "budget.latency": 0.0,
                                 "qos.target_reliability": "reliable", "qos.target_durability": "transient_local"}
# LiDAR maps: map mode with the place index (gravity-aligned maps, z up), the map voxelised to 0.2 m on load,
# one thread for a scan's alignments (small_gicp on 1,500 points: 25 ms per candidate on one thread against
# about 100 ms on two, on a 3.3 M-point training map under load); no slides for a scan whose fittest retrieved
# pose seats under 80 % of its points (verify_fitness: on the training world the fittest of every road scan
# seated 0.906 or more, of every off-map scan 0.735 or less), whose candidates GICP aligns by 3 iterations, not
# 30 (unfit_iterations: on the training world, 40 off-map scans rejected in 176 ms median against 241 at 30 and
# 205 at 5, road and indoor scans' results unchanged from 30 down to 2; at 1 an off-map scan was accepted).
# GICP on the map itself (MODEL_CARD: a coarser GICP map, tried for its load time, made two held-out indoor
# scans confidently wrong); tracking from the last pose moved on at the last two poses' velocity (predict_motion:
# on the training world a drive at 20 m/s tracked in 14 ms a scan against 205 from the last pose, each of whose
# scans moved beyond GICP's reach and was searched by the index; rooms keep the last pose: at 30 Hz a hand-held
# camera moves between frames about as much as two tracked poses differ by noise, so it changed little there);
# a pose found without a guess published at 0.8 or more (relocalize_confidence: on the training worlds, right ones
# at 0.53-0.65 or 0.87 and up, wrong ones at 0.50-0.76, five of them found while tracking was lost in a corridor);
# a scan enclosed as in a corridor not placed confidently without a guess (corridor_share: the share of directions
# with structure within 4 m was 0.00-0.37 for the training campuses' road scans, 0.53-0.85 for their corridor scans);
# an initialpose checked 4 m either way along a corridor (rough_reach: on the training campuses, surveyed every 3 m and
# every metre in corridors, corridor tracks from clicks 2 m and 10 deg off were never placed and 1-4 of 40 per map
# stayed 1.4-3.1 m off at 0.74-0.91; aligned again from poses along the corridor, 18-24 of 40 placed, none wrong;
# of clicks 0.3-2 m off the best pose was right for 419 and 0.26-0.30 m off for 11; a right one's distinct rival
# seated at most 0.970 of its points, a wrong one's 0.839: rough_rival 0.98 holds a tie only)
LIDAR_MAP_OVERRIDES: dict[str, Any] = {**MAP_OVERRIDES, "map.localization.retrieve": 8,
                                       "map.localization.map_voxel": 0.2, "map.localization.threads": 1,
                                       "map.localization.verify_fitness": 0.8, "map.localization.unfit_iterations": 3,
                                       "map.localization.flat_fit": 0.92, "map.predict_motion": True,
                                       "map.relocalize_confidence": 0.8, "map.localization.corridor_share": 0.45,
                                       "map.localization.rough_reach": 4.0}
PROFILES: dict[str, tuple[str, dict[str, Any]]] = {
    "genreg.yaml": (f"depth-camera and indoor scenes (the scene model {SCENE_MODEL})", SCENE_OVERRIDES),
    "genreg_lidar.yaml": (f"spinning LiDAR scans, pair mode (voxelised; slides along roads held; {SCENE_MODEL})",
                          LIDAR_OVERRIDES),
    "genreg_map.yaml": (f"map mode: depth-camera scans localised in a prior map (the scene model {SCENE_MODEL})",
                        MAP_OVERRIDES),
    "genreg_lidar_map.yaml": (f"map mode: LiDAR scans in a prior LiDAR map (z up; the place index; {SCENE_MODEL})",
                              LIDAR_MAP_OVERRIDES),
    "genreg_objects.yaml": (f"object models (the object model {OBJECT_MODEL}, clouds of a single object)", {}),
}
YAML_HEADER = """\
# Parameters of genreg_ros register_node for {purpose}. GENERATED from genreg_ros/config.py
# (and the core's config dataclasses): edit those, then run
#   .venv/bin/python -m genreg_ros.config --write
# Use:  .venv/bin/register_node --ros-args --params-file config/{name}
# Units: metres and seconds (REP-103); a distance of 0 means auto (derived from the clouds) where its
# comment says so. Empty lists / strings mean "off" / "from the message"; registration.seed -1 draws fresh
# randomness. Parameters marked (start-up) are read once; the others can be changed at run time
# (ros2 param set, or the node's set_parameters service).
"""


# ----------------------------------------------------------------------------- a setting's ROS value (no rclpy)
DOUBLE_ARRAY = "double_array"  # the ROS kind of a tuple/list setting


def optional_type(hint: Any) -> tuple[Any, bool]:
    """(the type inside Optional[...], whether it was optional)."""
    if typing.get_origin(hint) in (typing.Union, types.UnionType) and type(None) in typing.get_args(hint):
        return next(a for a in typing.get_args(hint) if a is not type(None)), True
    return hint, False


def ros_kind(s: Setting) -> Any:
    """bool, int, float, str or DOUBLE_ARRAY: the ROS type of a setting."""
    base, _ = optional_type(s.type)
    return DOUBLE_ARRAY if typing.get_origin(base) in (tuple, list) else base


def to_ros(s: Setting, value: Any) -> Any:
    """A setting's value as a ROS parameter value (ROS has no None: an optional integer is -1, a list [])."""
    if value is None:
        return -1 if ros_kind(s) is int else []
    return [float(v) for v in value] if ros_kind(s) is DOUBLE_ARRAY else value


def from_ros(s: Setting, value: Any) -> Any:
    """A ROS parameter value as the setting's value (inverse of `to_ros`)."""
    optional = optional_type(s.type)[1]
    if ros_kind(s) is DOUBLE_ARRAY:
        values = tuple(float(v) for v in (value or ()))
        return None if optional and not values else values
    return None if optional and value == -1 else value


# ----------------------------------------------------------------------------- the YAML text
def yaml_scalar(value: Any) -> str:
    """A parameter value as rcl's YAML reads it back with the same type (floats always have a dot)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(yaml_scalar(float(v)) for v in value) + "]"
    if isinstance(value, float):
        text = repr(value)
        if "e" in text and "." not in text:
            mantissa, exponent = text.split("e")
            text = f"{mantissa}.0e{exponent}"
        return text
    if isinstance(value, str):
        return value if value and value.replace("_", "").replace(".", "").isalnum() else f'"{value}"'
    return str(value)


def _comment(s: Setting) -> str:
    parts = ["(start-up)"] if s.start_up else []
    parts.append(s.help)
    if s.choices:
        parts.append(f"One of: {', '.join(s.choices)}.")
    elif s.low is not None and s.high is not None:
        parts.append(f"[{s.low:g}, {s.high:g}]")
    elif s.low is not None:
        parts.append(f"(>= {s.low:g})")
    if type(None) in typing.get_args(s.type):  # ROS has no None (to_ros)
        parts.append("ROS: -1 for None." if int in typing.get_args(s.type) else "ROS: [] for none.")
    return " ".join(parts)


def defaults(name: str = "genreg.yaml") -> dict[str, Any]:
    """Every setting's value in the shipped params file `name` (setting values, not ROS values)."""
    overrides = PROFILES[name][1]
    return {s.name: overrides.get(s.name, s.default) for s in SETTINGS}


def node_config(values: dict[str, Any]) -> NodeConfig:
    """The NodeConfig of setting values by name (missing ones keep their default). ConfigError names the
    first invalid setting."""
    nested: dict[str, Any] = {}
    for s in SETTINGS:
        *path, leaf = s.name.split(".")
        group = nested
        for part in path:
            group = group.setdefault(part, {})
        group[leaf] = values.get(s.name, s.default)
    return from_dict(NodeConfig, nested)


def profile_config(name: str = "genreg.yaml") -> NodeConfig:
    """The NodeConfig of the shipped params file `name` (a key of PROFILES)."""
    return node_config(defaults(name))


def yaml_text(name: str = "genreg.yaml") -> str:
    """The shipped params file `name` (a key of PROFILES): every parameter with its ROS value and a comment."""
    values = defaults(name)
    header = YAML_HEADER.format(purpose=PROFILES[name][0], name=name)
    lines, group = [header + "/**:", "  ros__parameters:"], ()
    for s in SETTINGS:
        *path, leaf = s.name.split(".")
        common = 0
        while common < min(len(path), len(group)) and path[common] == group[common]:
            common += 1
        for depth in range(common, len(path)):
            lines.append("    " + "  " * depth + f"{path[depth]}:")
        group = tuple(path)
        entry = "    " + "  " * len(path) + f"{leaf}: {yaml_scalar(to_ros(s, values[s.name]))}"
        lines.append(f"{entry:<40} # {_comment(s)}")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m genreg_ros.config", description=__doc__.split("\n\n")[0])
    action = p.add_mutually_exclusive_group(required=True)
    action.add_argument("--write", action="store_true", help=f"write {', '.join(PROFILES)} into config/")
    action.add_argument("--check", action="store_true", help="exit 1 if a shipped params file is out of date")
    args = p.parse_args(argv)
    stale = []
    for name in PROFILES:
        path, text = CONFIG_DIR / name, yaml_text(name)
        if args.write:
            path.write_text(text)
            print(f"wrote {path} ({len(SETTINGS)} parameters)")
        elif not path.is_file() or path.read_text() != text:
            stale.append(name)
    if stale:
        print(f"out of date: {', '.join(stale)}: run python -m genreg_ros.config --write", file=sys.stderr)
    return int(bool(stale))


if __name__ == "__main__":
    sys.exit(main())
