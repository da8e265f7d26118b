"""Typed configuration of genreg_core: the one home of every setting.

Each field is declared with `setting(default, help, low=..., high=..., choices=...)`: its name, default,
range and one-line help live here once. `settings(cls)` lists them (dotted names, nested dataclasses
flattened); the ROS node's parameters, their validation and `config/genreg.yaml` are derived from that
list. Dataclasses load from plain dicts (YAML) with `from_dict`, which rejects unknown keys and wrong
types with a `ConfigError` naming the field; `check_ranges` enforces the declared limits.

Units: distances in the registration settings are in the input's units (metres for sensor data,
REP-103); 0 means auto: a fixed fraction of the source cloud's robust extent (its bounding box without
the 0.1 % outermost points on each side, `prepare.robust_extent`), which is what the models were trained
at and what a stray point cannot stretch. `prepare.model_frame_config` turns them into the normalised
frame the network and PDSAC work in.
"""

from __future__ import annotations

import dataclasses
import math
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from genreg_core.errors import ConfigError
from genreg_core.refinement import REFINEMENTS

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA_ROOT = REPO_ROOT.parent / "shared" / "data"
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
# The shipped models loaded when none is named (MODEL_CARD.md): objects (since 2026-12-02, commit 7f8b38a, the
# DGCNN-only model: as accurate as the mixer model `modelnet40` on training pairs, half its time) and scenes.
OBJECT_MODEL = "modelnet40_dgcnn"
SCENE_MODEL = "7scenes"


AUTO_INLIER_THRESHOLD = 0.05  # PDSAC inlier residual, auto: this share of the source's robust extent
AUTO_ICP_DISTANCE = 0.05  # ICP correspondence distance, auto
AUTO_GUARD_DISTANCE = 0.5  # the refinement guard's ICP from identity, auto


def data_root(configured: str | os.PathLike | None = None) -> Path:
    """Dataset folder: `GENREG_DATA` if set, else `configured`, else ../shared/data beside the repo."""
    env = os.environ.get("GENREG_DATA")
    return Path(env or configured or DEFAULT_DATA_ROOT).expanduser()


def setting(
    default: Any,
    help: str,
    *,
    low: float | None = None,
    high: float | None = None,
    choices: tuple[str, ...] | None = None,
    start_up: bool = False,
) -> Any:
    """A dataclass field carrying its help and limits (inclusive). `start_up`: read once (a node restart
    changes it). Mutable defaults (lists, dataclass instances) are copied per instance."""
    meta = {"help": help, "low": low, "high": high, "choices": choices, "start_up": start_up}
    if isinstance(default, (list, dict)) or dataclasses.is_dataclass(default):
        return field(default_factory=lambda: dataclasses.replace(default) if dataclasses.is_dataclass(default)
                     else type(default)(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class Setting:
    """One setting as `settings()` lists it: dotted name, default, type hint, help and limits."""

    name: str
    default: Any
    type: Any
    help: str
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    start_up: bool = False


def settings(cls_or_obj: Any, prefix: str = "", start_up: bool = False) -> tuple[Setting, ...]:
    """Every leaf setting of a config dataclass (or instance: its values become the defaults), nested
    dataclasses flattened with dotted names ("refine.max_iterations"). A group declared `start_up` (or
    `start_up` given) makes each of its settings start-up."""
    cls = cls_or_obj if isinstance(cls_or_obj, type) else type(cls_or_obj)
    hints = typing.get_type_hints(cls)
    out: list[Setting] = []
    for f in dataclasses.fields(cls):
        if isinstance(cls_or_obj, type):
            value = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        else:
            value = getattr(cls_or_obj, f.name)
        m = f.metadata
        if dataclasses.is_dataclass(hints[f.name]):
            out += settings(value, f"{prefix}{f.name}.", start_up or m.get("start_up", False))
            continue
        out.append(Setting(f"{prefix}{f.name}", value, hints[f.name], m.get("help", ""), m.get("low"),
                           m.get("high"), m.get("choices"), start_up or m.get("start_up", False)))
    return tuple(out)


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ConfigError(message)


def check_ranges(obj: Any, prefix: str = "") -> None:
    """Raise ConfigError if a field of dataclass `obj` is outside its declared limits or choices."""
    for f in dataclasses.fields(obj):
        value, m, name = getattr(obj, f.name), f.metadata, f"{prefix}{f.name}"
        if isinstance(value, bool) or value is None:
            continue
        if m.get("choices") is not None and value not in m["choices"]:
            raise ConfigError(f"{name} must be one of {list(m['choices'])}, got {value!r}")
        if isinstance(value, (int, float)):
            low, high = m.get("low"), m.get("high")
            if (low is not None and value < low) or (high is not None and value > high):
                raise ConfigError(f"{name} must be in [{low}, {high}], got {value!r}")


@dataclass(frozen=True)
class ModelConfig:
    """Network architecture. Stored inside every checkpoint; `model.build_model` builds it.

    "genreg" (every shipped model): rotation-invariant point-pair-feature encoder, the paper's two mixer
    layers (or, backbone "dgcnn", a linear layer on the GCNN features) and the soft pointer that picks each
    point's match in the other cloud (`genreg_core.model.genreg`). "paper": the paper's own generator
    (T-Net, xyz GCNN, mixers, global feature interaction, decoder; `genreg_core.model.paper`), kept as a
    tested variant for ablations; its layer widths are the paper's, fixed in that module.
    """

    architecture: str = setting("genreg", "genreg (shipped) or paper (the paper's generator, ablations).",
                                choices=("genreg", "paper"))
    num_points: int = setting(512, "N: token mixing fixes it; the API resamples inputs to N.", low=32)
    k_neighbors: int = setting(20, "kNN graph size of the GCNN.", low=1)
    gcnn_channels: int = setting(64, "Edge-convolution output channels.", low=1)
    mixer_hidden: tuple[int, ...] = setting((1024, 128), "Hidden widths of mixer layer 1 and 2.")
    feature_dim: int = setting(128, "Per-point feature width after the mixers.", low=1)
    backbone: str = setting("pointmixer", "pointmixer: GCNN + the paper's two mixer layers; dgcnn: GCNN "
                            "features alone, then a linear layer.", choices=("pointmixer", "dgcnn"))
    attention_dim: int = setting(64, "Query/key width of the soft pointer (genreg).", low=1)
    point_feature: str = setting("centroid", "Per-point invariant beside the local covariance: centroid (distance "
                                 "to the cloud's centroid; moves when a cloud is cropped) or knn (mean distance "
                                 "to the k neighbours; local, crop-robust).", choices=("centroid", "knn"))
    generation: str = setting("pick", "pick: A_g is the best-matching point of B; neighbours: the match-weighted "
                              "mean of the pick's generation_k nearest neighbours in B (can leave B's samples; "
                              "rotation-equivariant by construction).", choices=("pick", "neighbours"))
    generation_k: int = setting(8, "Neighbours of the pick that generation 'neighbours' mixes.", low=2, high=64)
    overlap_head: bool = setting(False, "Per-point overlap score (supervised by the true overlap); PDSAC draws "
                                 "and scores with it.")
    norm: str = setting("group", "Normalisation in the point MLPs: group (statistics over each cloud's points, "
                        "which move when a cloud is cropped) or none (each point's features depend only on its "
                        "neighbourhood).", choices=("none", "group"))
    pointer_centring: bool = setting(True, "The soft pointer centres queries and keys on their cloud's mean (True; "
                                     "a statistic of the whole cloud) or on learned constants, its biases (False).")
    discriminator_hidden: tuple[int, ...] = setting((64, 128), "Discriminator per-point widths (training only).")

    def __post_init__(self) -> None:
        check_ranges(self, "model.")
        _check(self.k_neighbors < self.num_points, "model.k_neighbors must be < model.num_points")
        _check(len(self.mixer_hidden) == 2, "model.mixer_hidden needs two widths (one per mixer layer)")


@dataclass(frozen=True)
class PDSACConfig:
    """Parallel differentiable sample consensus (paper Sec. 3.3)."""

    num_hypotheses: int = setting(512, "PDSAC hypotheses m drawn at once.", low=1, high=100000)
    sample_size: int = setting(3, "PDSAC correspondences k per minimal set: 3, the fewest that fix a rigid motion, on "
                               "objects; 4 on depth-camera scenes.", low=3, high=64)
    inlier_threshold: float = setting(0.0, "PDSAC inlier residual, m (input units); 0: auto, 5 % of the "
                                      "source's robust extent.", low=0.0, high=1e4)
    temperature: float = setting(0.01, "Softmax temperature of the soft (training) selection.", low=1e-9)
    refit: bool = setting(True, "Least-squares refit on the winner's inliers (inference).")
    refit_tightening: tuple[float, ...] = setting((0.5, 0.25), "After the refit, one more refit at each of these "
                                                  "fractions of the inlier threshold: the tight rounds keep only the "
                                                  "closest correspondences ([]: none).")
    local_candidates: int = setting(4, "Best hypotheses of each direction refit once on their inliers among both "
                                    "directions' correspondences and compared there (LO-RANSAC's local "
                                    "optimisation; inference).", low=1, high=1000)
    modes: int = setting(4, "Distinct hypotheses (modes) verified: PDSAC's winner plus the best-scoring hypotheses "
                         "at least `mode_separation` apart from it and each other, each refit on its inliers, refined "
                         "and verified against the clouds (with a calibrated confidence, without an initial guess); "
                         "1: the winner alone.", low=1, high=64)
    modes_below: float = setting(0.9, "The other modes (and `passes`) are verified only when GenReg's refined "
                                 "estimate verifies below this confidence (1: always).", low=0.0, high=1.0)
    mode_separation: float = setting(15.0, "Two hypotheses are distinct modes when their rotations differ by more "
                                     "than this, deg, or their translations by more than a tenth of the source's "
                                     "extent.", low=0.0, high=180.0)

    def __post_init__(self) -> None:
        check_ranges(self, "pdsac.")
        _check(all(0.0 < f <= 1.0 for f in self.refit_tightening), "pdsac.refit_tightening: fractions in (0, 1]")

    @property
    def tau(self) -> float:
        """The inlier threshold in the units of the correspondences PDSAC is given (the pipeline hands it
        the normalised frame, `prepare.model_frame_config`): the value, or the auto value if 0."""
        return self.inlier_threshold or AUTO_INLIER_THRESHOLD


# PDSAC on depth-camera scenes: minimal sets of 4, not the default 3. A scene's 512 correspondences are
# dense and noisy; on kidnapped training pairs (redkitchen 0-799) 4 points per set gave lower mean errors
# and one more success in 40 at gap 60, where objects gained from 3 (MODEL_CARD "PDSAC settings"). The
# node's scene params file (config/genreg.yaml) and the benchmarks' scene datasets use it.
SCENE_PDSAC = PDSACConfig(sample_size=4)


@dataclass(frozen=True)
class RefineConfig:
    """Optional refinement after GenReg + PDSAC, and its guard.

    `method` is one of the refinement registry's (`genreg_core.refinement.REFINEMENTS`: the function that
    refines, the target it needs, whether the calibration serves it).

    Guard against a wrong global estimate (e.g. a symmetric shape flipped): without an initial guess, when
    the overlap score after refinement is below `guard_below`, the refinement also runs from identity with
    the wide cut-off `guard_distance` and `guard_iterations`; it replaces the pose when it puts more source
    points within one target spacing of the target (`score.TIGHT_SPACINGS`), and the result's `start` is
    then "guard". 0 turns the guard off. Chosen on training-split pairs (MODEL_CARD.md, "the refinement
    guard"). With an initial guess, refinement always runs from the guess too (with the refinement's own
    settings) and competes the same way, so an exact guess is kept.
    """

    method: str = setting("none", "Refinement after PDSAC: Open3D ICP point_to_point or point_to_plane, or "
                          "small_gicp's gicp.", choices=tuple(REFINEMENTS))
    max_iterations: int = setting(10, "ICP iterations.", low=1, high=1000)
    max_correspondence_distance: float = setting(0.0, "ICP correspondence distance, m (input units); 0: auto, "
                                                 "5 % of the source's robust extent.", low=0.0, high=1e4)
    num_points: int = setting(5000, "Points per cloud used by ICP and the fitness measure.", low=16,
                              high=1_000_000)
    guard_below: float = setting(0.4, "Without an initial guess, below this overlap score (the geometric mean of "
                                 "fitness, tight fitness and inlier ratio) ICP also runs from identity (the guard); "
                                 "the start with more source points within one target spacing wins (0: off).",
                                 low=0.0, high=1.0)
    guard_distance: float = setting(0.0, "ICP correspondence distance of the guard's run from identity, m; 0: "
                                    "auto, 50 % of the robust extent.", low=0.0, high=1e4)
    guard_iterations: int = setting(50, "ICP iterations of the guard's run from identity.", low=1, high=1000)
    fine_fraction: float = setting(1.0, "After the ICP iterations, `fine_iterations` more at this fraction of the "
                                   "correspondence distance: the wide distance finds the basin, the tight one "
                                   "keeps points outside the overlap from pulling the pose (1: one stage).",
                                   low=0.01, high=1.0)
    fine_iterations: int = setting(10, "ICP iterations of the tight stage (`fine_fraction` < 1).", low=1, high=1000)

    def __post_init__(self) -> None:
        check_ranges(self, "refine.")


@dataclass(frozen=True)
class FallbackConfig:
    """Opt-in classical global registration (`genreg_core.fallback`: Open3D FPFH + RANSAC) when GenReg stays
    unsure: below confidence `below` after refinement and guard, FPFH + RANSAC runs on the refinement
    clouds, is refined like GenReg's estimate, and replaces it when it puts more source points within one
    target spacing of the target (as the guard). The result's `start` then says "fallback". Lengths are
    fractions of the source's robust extent (the defaults are the unit-box baseline's, MODEL_CARD.md)."""

    method: str = setting("none", "Fallback below `below` confidence: none or fpfh_ransac (Open3D).",
                          choices=("none", "fpfh_ransac"))
    below: float = setting(0.3, "Run the fallback when the overlap score (as refine.guard_below) stays below this.",
                           low=0.0, high=1.0)
    voxel_size: float = setting(0.0, "Feature voxel, fraction of the extent (0: the refinement points as given).",
                                low=0.0, high=1.0)
    normal_radius: float = setting(0.1, "Normal radius, fraction of the extent.", low=1e-4, high=1.0)
    fpfh_radius: float = setting(0.25, "FPFH radius, fraction of the extent.", low=1e-4, high=1.0)
    distance: float = setting(0.05, "RANSAC inlier distance, fraction of the extent.", low=1e-4, high=1.0)
    seed: int = setting(0, "Open3D RANSAC seed.", low=0, high=2**31 - 1)

    def __post_init__(self) -> None:
        check_ranges(self, "fallback.")


@dataclass(frozen=True)
class RegistrationConfig:
    """Everything the registration pipeline needs besides the network weights."""

    pdsac: PDSACConfig = setting(PDSACConfig(), "PDSAC settings.")
    refine: RefineConfig = setting(RefineConfig(), "Refinement settings.")
    fallback: FallbackConfig = setting(FallbackConfig(), "Opt-in classical fallback.")
    min_points: int = setting(32, "Clouds with fewer finite points fail (TooFewPointsError).", low=4,
                              high=1_000_000)
    seed: int | None = setting(0, "Subsampling and PDSAC seed; None draws fresh randomness.")
    passes: int = setting(4, "Network passes while unsure (with a calibrated confidence, without an initial guess, "
                          "below `pdsac.modes_below`): each more pass registers another subsample with other PDSAC "
                          "draws (seed + 1, + 2, ...) and the result most probably right wins; 1: one pass.",
                          low=1, high=16)
    device: str = setting("cpu", "Torch device: cpu, cuda or cuda:<index>.", start_up=True)
    estimate_threads: int = setting(1, "Torch intra-op threads while the network and PDSAC run; 0: torch's own "
                                    "setting. One is faster on small clouds (MODEL_CARD.md).", low=0, high=256)
    slide_fit: float = setting(0.0, "A pose whose source seats at least this share of its own points within two target "
                               "spacings moved four target spacings along the aligned source's main axis, either way, is "
                               "named as well fitted along it (a road or a corridor alike along its length) and held at "
                               "1 - its confidence, at most 0.5; 0: off.", low=0.0, high=1.0)
    turn_fit: float = setting(0.0, "A confident pose (above 0.5, no initial guess) whose source seats at least this share "
                              "of its own tight fitness at a distinct pose turned 90, 180 or 270 deg about the sensor's "
                              "z axis and aligned again is named as well fitted turned (a corridor alike turned around) "
                              "and held at 1 - its confidence; 0: off.",
                              low=0.0, high=1.0)
    see_through: float = setting(0.0, "A confident pose (above 0.5) whose source, placed by it, would have seen through at "
                                 "least this share of the target's structure (its points 1 m or more above the source's "
                                 "ground, in front of the source's returns along their rays) is held at 1 - its "
                                 "confidence: a corridor's pose turned or slid puts walls where the source saw through "
                                 "doorways. The source in its sensor frame, z up (a level LiDAR), in metres; 0: off.",
                                 low=0.0, high=1.0)

    def __post_init__(self) -> None:
        check_ranges(self)
        _check(self.device == "cpu" or self.device == "cuda" or (
            self.device.startswith("cuda:") and self.device[5:].isdigit()),
            f"device must be cpu, cuda or cuda:<index>, got {self.device!r}")


# The scene profile (depth cameras, rooms, LiDAR): the scene model with GICP refinement and the scene PDSAC
# settings, best on real training pairs (MODEL_CARD.md). The node's scene params file, the benchmarks' scene
# datasets and the calibration scripts all start from it.
SCENE_REGISTRATION = RegistrationConfig(pdsac=SCENE_PDSAC, refine=RefineConfig(method="gicp", max_iterations=20,
                                                                                 fine_fraction=0.25), passes=1)


@dataclass(frozen=True)
class LocalizationConfig:
    """Localisation of scans in a prior map (`genreg_core.localization.MapLocalizer`; the module docstring
    describes the search). Lengths "in scan radii" are multiples of a scan's radius: the 90 % quantile of
    its voxelised points' distances from their centroid, rounded up to a power of `radius_step`. The
    defaults were chosen on redkitchen training frames 0-799 (MODEL_CARD.md, "Map relocalisation").

    Two thresholds here steer the search's effort, not whether a pose is accepted (the caller decides that
    from the result's confidence; the node by `min_confidence`): `accept_whole` (without a guess, no place
    search when the whole map's pose is this confident) and `track_below` (with a guess, GenReg checks a
    tracked pose this unsure)."""

    voxel_size: float = setting(0.0, "The map's resolution, m, to which each scan is voxelised; 0: auto, the "
                                "map's median nearest-neighbour spacing.", low=0.0, high=1e3)
    threads: int = setting(0, "Threads of tracking's GICP and of the place search's k-d tree queries; 0: "
                           "OMP_NUM_THREADS, else 1.", low=0, high=256)
    whole_map_ratio: float = setting(1.25, "Without a guess, the whole map's pose stands when the map's extent is "
                                     "below this times the scan's (0: places are always searched).",
                                     low=0.0, high=100.0)
    accept_whole: float = setting(0.9, "Without a guess, the whole map's pose also stands (no place search) when "
                                  "its confidence reaches this (1: places are searched unless the map is small).",
                                  low=0.0, high=1.0)
    part_gap: float = setting(0.5, "Without a guess, a map in parts (rooms or floors mapped apart: its points "
                              "joined where cells of this many scan radii touch) has its parts of at least "
                              "place_points points registered whole, in the order of the scan's screening against "
                              "each, until a pose stands, before places are searched (0: the map is one part).",
                              low=0.0, high=100.0)
    max_parts: int = setting(4, "A map in more parts than this (of at least place_points points) is registered "
                             "as one.", low=1, high=64)
    place_spacing: float = setting(0.5, "Candidate places are centred on the occupied cells of a grid with this "
                                   "spacing, in scan radii.", low=0.05, high=10.0)
    place_radius: float = setting(1.2, "A candidate place is the map within this many scan radii of its centre.",
                                  low=0.1, high=10.0)
    place_points: int = setting(4096, "A place keeps at most this many of its map points (a random subset; the "
                                "model samples its N of them).", low=32, high=100_000_000)
    radius_step: float = setting(1.25, "Scan radii are rounded up to powers of this, so that scans of similar "
                                 "size share one grid of places.", low=1.01, high=4.0)
    screen_model_points: int = setting(256, "Places are screened (registered unrefined, one mode) by the "
                                       "registrar's weights at this N.", low=32, high=4096)
    screen_points: int = setting(1000, "Screened places are scored on this many points.", low=16,
                                 high=1_000_000)
    batch_size: int = setting(16, "Places registered per batched network call.", low=1, high=1024)
    candidates: int = setting(3, "The best-screened places verified by registration from their pose against "
                              "the map around each (crop_radius).", low=1, high=1000)
    verify_above: float = setting(0.01, "A screened place is verified only if its screening confidence reaches "
                                  "this (0: always): the lowest of a place that verified right on redkitchen "
                                  "training maps was 0.017; a scan of another place screens below it and is "
                                  "rejected without verifying.", low=0.0, high=1.0)
    crop_radius: float = setting(1.5, "A verification, or GenReg from a guess, registers against the map within "
                                 "this many scan radii of the scan's predicted centre.", low=0.1, high=100.0)
    track_below: float = setting(0.5, "With a guess, a tracked pose (GICP) less confident than this is checked "
                                 "by GenReg from the guess on a crop (with the place index: by its search); "
                                 "the more confident pose wins (1: always).",
                                 low=0.0, high=1.0)
    track_points: int = setting(1500, "Tracking aligns and verifies at most this many of the voxelised scan's "
                                "points.", low=16, high=10_000_000)
    track_distance: float = setting(10.0, "Tracking's GICP correspondence distance, in map voxels (voxel_size).",
                                    low=0.5, high=1000.0)
    track_iterations: int = setting(30, "Tracking's GICP iterations.", low=1, high=1000)
    local_radius: float = setting(3.0, "Tracking's local map: the map within this many scan radii of the "
                                  "guessed scan centre.", low=0.5, high=1000.0)
    local_keep: float = setting(1.0, "The local map is kept while the guessed scan centre stays within this "
                                "many scan radii of its centre (below local_radius).", low=0.0, high=1000.0)
    map_voxel: float = setting(0.0, "The map is voxelised to this size, m, when it is loaded (0: used as "
                               "given).", low=0.0, high=1e3)
    retrieve: int = setting(0, "Without a guess, the place index of a gravity-aligned map (z up, as a LiDAR "
                            "map) retrieves this many places and headings; each is aligned and verified as a "
                            "tracked scan, and the most confident wins (0: no index; every place is screened "
                            "by GenReg instead).", low=0, high=1000)
    index_spacing: float = setting(1.0, "The place index's places: the free cells of a horizontal grid of this "
                                   "size, m.", low=0.1, high=100.0)
    index_radius: float = setting(30.0, "The place index describes the map within this distance, m, of each "
                                  "place (and a scan within it of its sensor).", low=1.0, high=1000.0)
    index_band: float = setting(2.0, "The place index's descriptors see structure up to this height, m, above "
                                "the local ground (ceilings and canopies above it are left out).",
                                low=0.1, high=100.0)
    screen_voxels: float = setting(5.0, "Retrieved places are aligned coarsely (VGICP) on voxels this many map "
                                   "voxels wide.", low=1.0, high=1000.0)
    slide_reach: float = setting(14.0, "The fittest retrieved pose is also tried slid along the scan's main axis "
                                 "(a road, a corridor) by every two VGICP voxels up to this distance, m, both "
                                 "ways: a look-alike pose found there is its rival (0: off).", low=0.0, high=1000.0)
    verify_fitness: float = setting(0.0, "With the place index, when no retrieved place's coarse (VGICP) alignment "
                                    "seats this share of the scan's screened points, the fittest is not slid along "
                                    "the scan's axis (slide_reach): a scan the map does not hold is rejected "
                                    "sooner; its candidates are still verified (0: always slid).",
                                    low=0.0, high=1.0)
    unfit_iterations: int = setting(30, "With the place index, the GICP iterations that align the candidates of a "
                                    "scan no retrieved place fits (verify_fitness): a scan the map does not hold "
                                    "never converges, and is rejected sooner with fewer (track_iterations: as "
                                    "tracked).", low=1, high=1000)
    flat_fit: float = setting(0.0, "A tracked pose that seats at least this share of its own tight fitness when "
                              "moved 3 map spacings either way along the scan's main horizontal axis (a uniform "
                              "corridor) is named unconstrained along it, its covariance widened by that shift, "
                              "and aligned again from the best fit found up to 3 spacings either way, half a "
                              "spacing apart (GICP from a guess stops on a ripple of such a valley); "
                              "found without a guess (the place index), its confidence is also held at 1 - its "
                              "own; tracked outside a corridor (corridor_share), it lies on a plateau short of the "
                              "place and is checked by the place index as an unsure track is (0: off).",
                              low=0.0, high=10.0)
    rough_reach: float = setting(0.0, "A rough guess (an operator's initialpose: localize(..., rough=True)) may be "
                                 "this far off, m: a confident track from it in a flat valley (flat_fit) or moved "
                                 "beyond GICP's reach is aligned again from poses along the scan's main horizontal "
                                 "axis up to this far either way (a corridor, where GICP from a click metres off "
                                 "stays near it or slides to a look-alike fit) and the pose that seats the most "
                                 "points wins (rough_rival); a pose so checked counts as tracked from the guess "
                                 "(0: off).", low=0.0, high=100.0)
    rough_rival: float = setting(0.98, "Of a rough guess's poses along the corridor (rough_reach), one distinct from "
                                 "the best that seats at least this share of its points is its rival: the fits do "
                                 "not tell where along the corridor the scan is; the best is named with it and its "
                                 "confidence held at 1 - its own.", low=0.0, high=10.0)
    corridor_share: float = setting(0.0, "A scan that has structure (0.3 m to index_band above its ground) within "
                                    "4 m of the sensor in at least this share of directions is in a corridor, which "
                                    "one scan cannot tell from look-alike corridors: a pose searched for there (the "
                                    "place index's, without a guess or checking an unsure track; a track found "
                                    "beyond tracking's reach of its guess) is named so and its confidence held at "
                                    "1 - its own (at most 0.5); a confident track within reach is kept (0: off).",
                                    low=0.0, high=1.0)
    map_threads: int = setting(0, "Threads that prepare the map for the place index's GICP and VGICP on load "
                               "(its k-d trees and covariances: the same result on any number); 0: "
                               "OMP_NUM_THREADS, else 1.", low=0, high=256)
    rival_distance: float = setting(4.0, "Two map poses whose positions differ by more than this many map voxels "
                                    "(or turned by more than PDSAC's mode separation) are distinct: the less "
                                    "probable bounds the other's confidence (a slide along a road or a "
                                    "corridor).", low=0.5, high=1e4)

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):  # every field is a number: an integer, or a finite float
            value, integer = getattr(self, f.name), hints[f.name] is int
            _check(isinstance(value, int if integer else (int, float)) and not isinstance(value, bool)
                   and (integer or math.isfinite(value)),
                   f"localization.{f.name} must be {'an integer' if integer else 'a finite number'}, got {value!r}")
        check_ranges(self, "localization.")
        _check(self.local_keep < self.local_radius,
               f"localization.local_keep ({self.local_keep}) must be below localization.local_radius "
               f"({self.local_radius})")


T = TypeVar("T")


def from_dict(cls: type[T], values: dict[str, Any] | None) -> T:
    """Build dataclass `cls` from a dict: unknown keys and wrong types raise ConfigError."""
    values = dict(values or {})
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - names)
    if unknown:
        raise ConfigError(f"{cls.__name__}: unknown key(s) {unknown}; allowed: {sorted(names)}")
    kwargs = {name: _coerce(cls.__name__, name, hints[name], value) for name, value in values.items()}
    return cls(**kwargs)


def _coerce(owner: str, name: str, hint: Any, value: Any) -> Any:
    origin = typing.get_origin(hint)
    if dataclasses.is_dataclass(hint):
        if not isinstance(value, dict):
            raise ConfigError(f"{owner}.{name} must be a mapping, got {type(value).__name__}")
        return from_dict(hint, value)
    if origin in (typing.Union, types.UnionType):
        args = typing.get_args(hint)
        if value is None and type(None) in args:
            return None
        hint = next(a for a in args if a is not type(None))
        origin = typing.get_origin(hint)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{owner}.{name} must be a list, got {type(value).__name__}")
        item = typing.get_args(hint)[0]
        return tuple(_coerce(owner, name, item, v) for v in value)
    if hint is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if hint in (int, float, str, bool) and not (
        isinstance(value, hint) and not (hint is not bool and isinstance(value, bool))
    ):
        raise ConfigError(f"{owner}.{name} must be {hint.__name__}, got {value!r}")
    return value
