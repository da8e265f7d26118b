"""register_node's pipelines: what becomes of one pair, one pipeline per kind of target, one interface.

The node chooses its pipeline once, at configure (`make_pipeline`), and its worker threads hand it the pairs
(`Pipeline.process`); nothing on that path asks which mode the node is in. The pipelines:
- `PairPipeline`: the target comes from the target_cloud topic, paired by stamp (sync.mode approximate) or
  the newest one (sync.mode latest_target, a run-time parameter; a reused target is decoded and preprocessed
  once). Each pair is registered from the start `genreg_ros.tracking` gives, in full or light
  (`genreg_ros.budget`: the latency budget).
- `FixedTargetPipeline`: the same against `target_file`'s cloud, read at configure (target_cloud is not
  subscribed; every source is paired with it).
- `MapPipeline` (map.enabled): each scan localised in a prior map (`target_file`, or the newest target_cloud,
  e.g. a latched map; not preprocessed) by the core's MapLocalizer, globally or from a guess as the map state
  says (`genreg_ros.map_state`: global, tracking, lost).

Every pair handed to `process` gets one answer, its `Publication`: a result's registration_status and,
unless the policy rejects it (`genreg_ros.policy`), its outputs; a pair that is not registered (a cloud that
cannot be decoded, a registration error, an unexpected exception) is counted (dropped.<reason>,
failed.<reason>) and answered by a status alone. A pipeline keeps the registration settings in force as one
object while they are unchanged and assigns them to a registrar only when they change (new parameters, or
the budget switching between full and light). Thread-safe: each `process` call uses a registrar no other
call is using (the node runs one worker thread per registrar).
"""

from __future__ import annotations

import queue
import re
import threading
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Literal

import numpy as np

from genreg_core.config import RegistrationConfig
from genreg_core.errors import GenRegError, TooFewPointsError
from genreg_core.geometry import apply_transform
from genreg_core.preprocess import PreprocessConfig, preprocess
from genreg_ros.budget import LatencyBudget
from genreg_ros.config import NodeConfig
from genreg_ros.diagnostics import Reporter
from genreg_ros.intake import CloudPair, FixedTarget, Target
from genreg_ros.map_state import LOST, TRACKING, Localization, Step, placement, scan_start
from genreg_ros.pointcloud2 import DecodedCloud, PointCloud2Error, read_points
from genreg_ros.policy import Verdict, judge
from genreg_ros.publication import Outputs, Publication, Statuses, pair_header
from genreg_ros.registrar import Registering
from genreg_ros.sync import PairSync
from genreg_ros.tracking import Start, Tracker, motion_continues

if TYPE_CHECKING:
    from collections.abc import Callable

    from genreg_core.localization import MapLocalizer
    from genreg_core.registration import Registrar
    from genreg_core.result import RegistrationResult


def _snake(name: str) -> str:
    return re.sub(r"(?<!^)(?=[A-Z])", "_", name.removesuffix("Error")).lower()


def failure_reason(exc: GenRegError) -> str:
    """The `failed.<reason>` of a registration error: too_few_points for every TooFewPointsError (its subclass
    NonFinitePointsError included), else the exception's class name in snake case (CheckpointError: checkpoint)."""
    return "too_few_points" if isinstance(exc, TooFewPointsError) else _snake(type(exc).__name__)


@dataclass(frozen=True)
class Context:
    """What a pipeline shares with its node."""

    config: Callable[[], NodeConfig]  # the settings in force (replaced, never mutated, when parameters change)
    tracker: Tracker  # topic guesses and the last result
    report: Reporter  # counted drops and failures, warnings
    statuses: Statuses  # registration_status messages


@dataclass(frozen=True)
class Prepared:
    """A pair's decoded and preprocessed clouds, with the time spent decoding and preprocessing (s)."""

    source: DecodedCloud  # every field is kept in the aligned cloud
    source_points: np.ndarray  # preprocessed
    target_points: np.ndarray  # preprocessed (a map: as decoded)
    decode_s: float
    preprocess_s: float
    base_T_source: np.ndarray | None = None  # base_frame: the source points were moved into it by this


class NotRegistered(Exception):
    """A pair that is not registered: counted as `counter` (dropped or failed) `.reason`, answered by a status
    alone; `text` says why."""

    def __init__(self, counter: Literal["dropped", "failed"], reason: str, text: str) -> None:
        super().__init__(text)
        self.counter, self.reason, self.text = counter, reason, text


def figures(prepared: Prepared, result: RegistrationResult, start_s: float, register_s: float) -> dict[str, float]:
    """A registered pair's figures for the statistics (`start_s`: choosing the start, s). `guess_won`: the
    pose grew from the initial guess; `guard_won`: from the guard's ICP from identity (a core that labels it
    "initial_guess" counts it as guess_won)."""
    return {
        "fitness": result.fitness, "confidence": result.confidence, "inlier_rmse_m": result.inlier_rmse,
        "decode_ms": 1e3 * prepared.decode_s, "preprocess_ms": 1e3 * (prepared.preprocess_s + start_s),
        "register_ms": 1e3 * register_s,
        "points_in": float(prepared.source.num_input), "points_registered": float(len(prepared.source_points)),
        "points_target": float(len(prepared.target_points)),
        "guess_won": float(result.start == "initial_guess"), "guard_won": float(result.start == "guard"),
    }


class Pipeline(ABC):
    """One pair in, one Publication out (`process`), plus what the node's services and diagnostics ask."""

    fixed: FixedTarget | None = None  # the target read from a file (target_cloud is then not subscribed)

    def __init__(self, context: Context, registrars: list[Registering]) -> None:
        self._ctx = context
        self._free: queue.SimpleQueue[Registering] = queue.SimpleQueue()  # registrars no call is using
        for r in registrars:
            self._free.put(r)
        self._lock = threading.Lock()
        self._settings_of: tuple[NodeConfig | None, RegistrationConfig | None] = (None, None)
        self._target_cache: tuple[Target, PreprocessConfig | None, np.ndarray] | None = None

    # ------------------------------------------------------------------ the interface
    def process(self, pair: CloudPair) -> Publication:
        """Decode, preprocess, register and judge one pair with a free registrar: what it publishes."""
        registrar = self._free.get()
        try:
            return self._process(pair, registrar)
        except NotRegistered as exc:
            return self._unanswered(pair, exc.counter, exc.reason, exc.text)
        except Exception as exc:  # noqa: BLE001 (one pair must never stop a worker)
            return self._unanswered(pair, "failed", "internal_error", f"unexpected {type(exc).__name__}: {exc}")
        finally:
            self._free.put(registrar)

    def pairing(self, c: NodeConfig) -> PairSync:
        """The stamp pairing of this pipeline under `c` (`genreg_ros.sync`)."""
        return PairSync(c.sync.slop, c.sync.queue_size, c.sync.mode)

    @property
    def localization(self) -> str:
        """Map mode's state (global, tracking, lost); "" for the other pipelines."""
        return ""

    def reset(self) -> None:
        """Forget the pipeline's own state of the scene (the tracker is reset by the node)."""

    def relocalize(self, why: str) -> bool:
        """Localise the next scan without a guess; False if this pipeline has no such thing (not map mode)."""
        return False

    def map_cloud(self) -> tuple[np.ndarray, str] | None:
        """The map read from `target_file` as map mode localises in it and its frame (None: no such map)."""
        return None

    def describe(self, target_topic: str) -> str:
        """What the node registers against, for its start-up log line."""
        if self.fixed is not None:
            return f"target file {self.fixed.path} ({len(self.fixed.xyz)} points, frame {self.fixed.frame})"
        return f"target {target_topic}"

    # ------------------------------------------------------------------ steps
    @abstractmethod
    def _process(self, pair: CloudPair, registrar: Registering) -> Publication:
        """The pair's publication; NotRegistered for a pair that is not registered."""

    def _prepare(self, pair: CloudPair, c: NodeConfig, target_preprocess: PreprocessConfig | None) -> Prepared:
        """The pair's clouds decoded and preprocessed (the target with `target_preprocess`, None: as decoded)."""
        t0 = time.perf_counter()
        try:
            src = read_points(pair.source.msg, c.max_points)
        except PointCloud2Error as exc:
            raise NotRegistered("dropped", exc.reason, f"source cloud: {exc}") from None
        t1 = time.perf_counter()
        try:
            target_points, t_target = self._target(pair.target, c.max_points, target_preprocess)
        except PointCloud2Error as exc:
            raise NotRegistered("dropped", exc.reason, f"target cloud: {exc}") from None
        source_points = preprocess(src.points, c.preprocess)  # range and crop: the sensor's own frame
        base_T_source = c.base_T_source_matrix()
        if base_T_source is not None:  # localise base_frame: the cloud moved into it
            source_points = apply_transform(base_T_source, source_points)
        t2 = time.perf_counter()
        return Prepared(src, source_points, target_points, (t1 - t0) + t_target, (t2 - t1) - t_target, base_T_source)

    def _target(self, target: Target, max_points: int, pre: PreprocessConfig | None) -> tuple[np.ndarray, float]:
        """The target's points, preprocessed with `pre` (None: as decoded), and the decoding time; cached while
        the same target is reused (latest_target, target_file, a map)."""
        cache = self._target_cache
        if cache is not None and cache[0] is target and cache[1] == pre:
            return cache[2], 0.0
        t0 = time.perf_counter()
        points = target.points(max_points)
        t_decode = time.perf_counter() - t0
        points = points if pre is None else preprocess(points, pre)
        self._target_cache = (target, pre, points)
        return points, t_decode

    def _settings(self, c: NodeConfig) -> RegistrationConfig:
        """The registration settings of `c`, as the same object while they are unchanged (a parameter change
        that leaves them as they were keeps it)."""
        with self._lock:
            node, settings = self._settings_of
            if node is not c:
                fresh = c.registration_config()
                settings = settings if settings == fresh else fresh
                self._settings_of = (c, settings)
            return settings

    def _start(self, c: NodeConfig, pair: CloudPair, tracking: bool | None = None, parameter: bool = True,
               stamped: bool = False) -> Start:
        """The pair's start (`Tracker.start`; `stamped` (map mode): the last result moved to the pair's source
        stamp by the odometry, or with `map.predict_motion` on at the last two results' velocity); a topic guess
        discarded on the way is logged (expired) or counted as a drop (frames that are not the pair's)."""
        start = self._ctx.tracker.start(c, pair.source.frame, pair.target.frame, time.monotonic(),
                                        tracking=tracking, parameter=parameter,
                                        stamp=pair.source_stamp if stamped else None, predict=c.map.predict_motion)
        if start.discarded == "expired":
            self._ctx.report.info(start.note)
        elif start.discarded:
            self._ctx.report.drop(start.discarded, start.note)
        return start

    def _answer(self, pair: CloudPair, prepared: Prepared, result: RegistrationResult, verdict: Verdict,
                start: Start, generation: int, times: tuple[float, float], light: bool = False,
                registered_decoded: bool = False, jumped: bool = False) -> Publication:
        """A registered pair's publication: its status and, if the verdict publishes it, its outputs (the result
        is then kept for tracking); a rejected result is counted as failed. `times`: choosing the start and
        registering, s; `jumped`: the result lies beyond tracking's reach of its start (`motion_continues`)."""
        c, ctx = self._ctx.config(), self._ctx
        header = pair_header(pair)
        latency = time.monotonic() - max(pair.source.received, pair.target.received)
        status = ctx.statuses.result(result, header, pair.source.frame, start.origin, latency, verdict, light)
        if not verdict.publish:
            ctx.report.fail(verdict.reason, verdict.why)
            return Publication(status)
        if verdict.low_confidence:  # published, yet flagged: a user must not mistake it for a good result
            ctx.report.warn("low_confidence", f"published a low-confidence result: confidence {result.confidence:.2f} "
                            f"< warn_confidence {c.warn_confidence} (fitness {result.fitness:.2f})")
        ctx.tracker.record(result.transformation, pair.source_stamp, generation, time.monotonic(),
                           continues=motion_continues(start.origin, jumped), placed=verdict.jumped)
        # the odometry at the stamp again: messages that came meanwhile may now bracket it
        odom = ctx.tracker.odometry.at(pair.source_stamp, pair.source.frame) if c.map.odometry else None
        return Publication(status, Outputs(header, prepared.source, pair.source.frame, result, latency,
                                           prepared.decode_s, figures(prepared, result, *times),
                                           verdict.low_confidence, registered_decoded, prepared.base_T_source, odom))

    def _unanswered(self, pair: CloudPair, counter: Literal["dropped", "failed"], reason: str,
                    text: str) -> Publication:
        self._ctx.report.count(counter, reason, text)
        return Publication(self._ctx.statuses.unanswered(pair, "error", counter, reason, text))


class PairPipeline(Pipeline):
    """Each source registered against its pair's target (a cloud of the target_cloud topic)."""

    def __init__(self, context: Context, registrars: list[Registering]) -> None:
        super().__init__(context, registrars)
        self._budget = LatencyBudget()  # full or light registration per pair (budget.latency)

    def _process(self, pair: CloudPair, registrar: Registering) -> Publication:
        c = self._ctx.config()
        prepared = self._prepare(pair, c, c.preprocess)
        t0 = time.perf_counter()
        generation = self._ctx.tracker.generation
        start = self._start(c, pair)
        age = time.monotonic() - max(pair.source.received, pair.target.received)
        light, settings = self._budget.plan(age, self._settings(c), c.budget.latency, c.budget.light_points)
        if registrar.config is not settings:
            registrar.config = settings
        if light:
            self._ctx.report.stats.event("light")
        t1 = time.perf_counter()
        try:
            result = registrar.register(prepared.source_points, prepared.target_points, initial_guess=start.T)
        except GenRegError as exc:
            raise NotRegistered("failed", failure_reason(exc), f"registration failed: {exc}") from None
        t2 = time.perf_counter()
        self._budget.record(light, t2 - t1)
        return self._answer(pair, prepared, result, judge(result, c), start, generation, (t1 - t0, t2 - t1), light,
                            registered_decoded=prepared.source_points is prepared.source.points)


class FixedTargetPipeline(PairPipeline):
    """Each source registered against one target read from a file (`target_file`)."""

    def __init__(self, context: Context, registrars: list[Registering], fixed: FixedTarget) -> None:
        super().__init__(context, registrars)
        self.fixed = fixed

    def pairing(self, c: NodeConfig) -> PairSync:
        """Every source paired with the file's cloud."""
        sync = PairSync(c.sync.slop, c.sync.queue_size, "latest_target")
        sync.add_target(0, self.fixed)
        return sync


class MapPipeline(Pipeline):
    """Each scan localised in a prior map with the core's MapLocalizer, in the node's process (one registrar);
    the map state (global, tracking, lost) chooses how."""

    def __init__(self, context: Context, registrar: Registrar, fixed: FixedTarget | None,
                 cache_dir: Path | None = None) -> None:
        """`fixed`: the map read from `target_file` (None: the newest target_cloud); `cache_dir`: where
        MapLocalizer keeps the map's candidate places (beside a map file)."""
        super().__init__(context, [registrar])
        self.fixed = fixed
        self._cache_dir = cache_dir
        self._state = Localization(context.config().map.lost_after)
        self._localizer: tuple[np.ndarray, MapLocalizer, str] | None = None  # (map points, localizer, frame)
        if fixed is not None:  # a map file is prepared and warmed up before the node is ready, not on the first scan
            try:
                localizer = self._map_localizer(registrar, context.config(), fixed.xyz, fixed.frame)
                localizer.prepare()
                t0 = time.perf_counter()
                localizer.warm_up()
                self._ctx.report.info(f"map warmed up in {time.perf_counter() - t0:.1f} s (a piece of it localised, "
                                      "so that the first scan does not load compiled kernels)")
            except NotRegistered:
                pass  # the first scan meets the same error and counts it

    def pairing(self, c: NodeConfig) -> PairSync:
        """Every scan paired with the newest map (or the file's)."""
        sync = PairSync(c.sync.slop, c.sync.queue_size, "latest_target")
        if self.fixed is not None:
            sync.add_target(0, self.fixed)
        return sync

    @property
    def localization(self) -> str:
        return self._state.state

    def reset(self) -> None:
        self._state.relocalize()

    def relocalize(self, why: str) -> bool:
        """Forget the pose and topic guesses: the next scan is localised globally."""
        self._ctx.tracker.reset()
        self._state.relocalize()
        self._ctx.report.stats.event("relocalize")
        self._ctx.report.info(f"relocalize ({why}): the next scan is localised in the map without a guess")
        return True

    def map_cloud(self) -> tuple[np.ndarray, str] | None:
        if self.fixed is None or self._localizer is None:
            return None
        _, localizer, frame = self._localizer
        return localizer.map, frame

    def describe(self, target_topic: str) -> str:
        return f"map mode: localising scans in the map, {super().describe(target_topic)}"

    def _process(self, pair: CloudPair, registrar: Registering) -> Publication:
        c = self._ctx.config()
        prepared = self._prepare(pair, c, None)  # a map is not preprocessed: range and crop are the sensor's
        t0 = time.perf_counter()
        localizer = self._map_localizer(registrar, c, prepared.target_points, pair.target.frame)
        generation = self._ctx.tracker.generation
        before = self._state.step()  # global (no pose known: global or lost) or tracking
        step, start = scan_start(before, self._start(c, pair, tracking=True, parameter=False, stamped=True),
                                 keep=c.map.localization.retrieve > 0)
        t1 = time.perf_counter()
        try:
            result = localizer.localize(prepared.source_points, initial_guess=start.T, rough=start.rough)
        except GenRegError as exc:
            self._outcome(c, step, hit=False)
            raise NotRegistered("failed", failure_reason(exc), f"localisation failed: {exc}") from None
        t2 = time.perf_counter()
        # a pose beyond tracking's reach of its start was found elsewhere (the place index): while no pose is known
        # (global, lost) a relocalisation; from a predicted start, the motion broke off (a kidnap): the next scan's
        # prediction does not go on with it (`motion_continues`)
        moved = placement(before, start, start.T is None or localizer.within_reach(result.transformation, start.T, start.rough))
        verdict = judge(result, c, relocalized=moved.relocalized)
        # a miss: not published; a published pose not tracked from its start is a jump (`jumped`, `pose_jumps`)
        verdict = replace(verdict, localization=self._outcome(c, step, hit=verdict.publish), jumped=moved.jumped)
        if verdict.publish and verdict.jumped:
            self._ctx.report.stats.event("pose_jumps")
        # the registered points are the scan voxelised to the map's resolution, not the decoded ones
        return self._answer(pair, prepared, result, verdict, start, generation, (t1 - t0, t2 - t1),
                            jumped=moved.left)

    def _map_localizer(self, registrar: Registering, c: NodeConfig, map_points: np.ndarray,
                       frame: str) -> MapLocalizer:
        """The MapLocalizer of this map (built on the first scan after a new map or new registration settings,
        with the node's registrar); a map in another frame than the last one relocalises. NotRegistered if the
        map cannot be used (counted as failed)."""
        from genreg_core.localization import MapLocalizer

        settings = self._settings(c)
        if registrar.config is not settings:
            registrar.config = settings
            self._localizer = None  # its screening settings derive from the registrar's
        cached = self._localizer
        if cached is not None and cached[0] is map_points:
            return cached[1]
        try:
            localizer = MapLocalizer(map_points, registrar=registrar, config=c.map.localization,
                                     cache_dir=self._cache_dir)
        except GenRegError as exc:
            raise NotRegistered("failed", failure_reason(exc), f"the map cannot be used: {exc}") from None
        if cached is not None and cached[2] != frame:
            self.relocalize(f"the map's frame changed from '{cached[2]}' to '{frame}'")
        self._localizer = (map_points, localizer, frame)
        self._ctx.report.info(f"map of {len(map_points)} points in frame '{frame}' ready (resolution "
                              f"{localizer.voxel_size:.3g} m)")
        return localizer

    def _outcome(self, c: NodeConfig, step: Step, hit: bool) -> str:
        """Record a scan's outcome in the map state; the state it is reported in (logged when it changes)."""
        before = self._state.state
        state = self._state.update(step, hit, c.map.lost_after)
        after = self._state.state
        if after == LOST and before != LOST:
            self._ctx.report.stats.event("tracking_lost")
            self._ctx.report.logger.warning(f"map mode: tracking lost after {self._state.misses} missed scan(s) "
                                            "(map.lost_after); the next scan is localised without a guess")
        elif after == TRACKING and before != TRACKING:
            self._ctx.report.info(f"map mode: localised ({step.mode}), tracking")
        return state


def make_pipeline(c: NodeConfig, context: Context, registrars: list[Registering],
                  fixed: FixedTarget | None) -> Pipeline:
    """The pipeline of `c`: map mode (map.enabled; workers 1, the core's Registrar), a fixed target (`fixed`,
    read from target_file) or pairs of the two topics."""
    if c.map.enabled:
        from genreg_core.registration import Registrar

        (registrar,) = registrars
        if not isinstance(registrar, Registrar):
            raise TypeError("map mode localises in the node's process (workers 1)")
        cache = None if not c.target_file else Path(c.target_file).expanduser().with_name(
            Path(c.target_file).name + ".genreg-cache")  # a map file's candidate places, kept beside it
        return MapPipeline(context, registrar, fixed, cache)
    if fixed is not None:
        return FixedTargetPipeline(context, registrars, fixed)
    return PairPipeline(context, registrars)
