"""register_node's counters, its warnings about them and its /diagnostics status (one DiagnosticStatus per
node).

`Stats` is written by the subscription callbacks, the workers and the publisher (thread-safe); `Reporter`
counts a drop or failure there with its reason and warns about it (throttled per reason); `build_status`
turns one snapshot of the counters into the status: level WARN when a cloud topic is stale, the last pair
failed or its confidence was below warn_confidence; values as listed in docs/ros_node.md. `InputWatch` finds
input topics that stay silent although a publisher is matched (large best-effort clouds lost between
processes, a publisher that stopped) and says the likely cause once per silence. `Sequences` counts the clouds
a publisher sent that never reached the node, from the gaps in its messages' sequence numbers.
"""

from __future__ import annotations

import threading
import time
from collections import Counter, OrderedDict, deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from diagnostic_msgs.msg import DiagnosticStatus, KeyValue

from genreg_ros.sync import SOURCE, TARGET

if TYPE_CHECKING:
    from rclpy.topic_endpoint_info import TopicEndpointInfo

PUBLISHERS_KEPT = 64  # publishers per topic whose last sequence number is kept (the least recent forgotten)
WARN_THROTTLE_S = 2.0  # one warning per drop/failure reason this often, s
DOCS = "docs/ros_node.md"


class Logger(Protocol):
    """What the node's counters log through (an rclpy logger)."""

    def info(self, message: str) -> object: ...

    def warning(self, message: str) -> object: ...


class Sequences:
    """The messages one topic's publishers sent that never reached the subscription: the gaps in each
    publisher's publication sequence numbers (the rmw's message info, per publisher gid), whatever dropped
    them: the subscription's queue (`qos.depth`) overflowing while the process took no messages, or the
    transport. Counted from the first message received from each publisher (what it sent before is not the
    node's) and only while the subscription lives (`clear` when it is made anew). A middleware that gives
    no sequence numbers leaves the count at 0 (`counted` stays False)."""

    def __init__(self) -> None:
        self.last: OrderedDict[bytes, int] = OrderedDict()  # publisher gid -> its last sequence number received
        self.counted = False

    def missed(self, info: dict[str, Any] | None) -> int:
        """How many messages of this message's publisher were skipped since its last received one (0 for
        its first, an older or repeated one, or a message without a sequence number or gid)."""
        number = None if info is None else info.get("publication_sequence_number")
        gid = None if info is None else info.get("publisher_gid")
        if number is None or not gid:
            return 0
        self.counted = True
        key = bytes(gid["data"]) if isinstance(gid, dict) else bytes(gid)
        last = self.last.pop(key, None)
        self.last[key] = number if last is None else max(last, number)
        if len(self.last) > PUBLISHERS_KEPT:
            self.last.popitem(last=False)
        return 0 if last is None else max(0, number - last - 1)

    def clear(self) -> None:
        self.last.clear()


class Stats:
    """Thread-safe counters and recent figures behind /diagnostics."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.start = time.monotonic()
        self.received: Counter[str] = Counter()
        self.lost: Counter[str] = Counter()  # topic -> messages the middleware reported lost
        self.missed: Counter[str] = Counter()  # topic -> messages sent but never received (`Sequences`)
        self.sequences = {SOURCE: Sequences(), TARGET: Sequences()}
        self.dropped: Counter[str] = Counter()
        self.failed: Counter[str] = Counter()
        self.events: Counter[str] = Counter()  # time_jump, reset, light; map mode: relocalize, tracking_lost, pose_jumps
        self.registered = 0
        self.low_confidence = 0  # registered and published, but below warn_confidence
        self.paired = 0  # pairs formed by the sync; each is registered, failed, dropped or superseded
        self.last_arrival: dict[str, float | None] = {SOURCE: None, TARGET: None}
        self.latency = deque(maxlen=100)  # s, arrival of the pair's later cloud -> published
        self.overhead = deque(maxlen=100)  # s, node work besides preprocessing and registration
        self.callback = deque(maxlen=200)  # s, one cloud subscription callback (checks + pairing)
        self.last: dict[str, float] = {}
        self.last_outcome = ""  # "", "registered", "registered with low confidence" or "failed: <reason>"

    def arrived(self, topic: str, now: float, info: dict[str, Any] | None = None) -> int:
        """Count a cloud received on `topic` (`info`: its rmw message info) and return how many of its
        publisher's clouds were missed before it (`Sequences.missed`, added to `missed`)."""
        with self.lock:
            self.received[topic] += 1
            self.last_arrival[topic] = now
            missed = self.sequences[topic].missed(info)
            self.missed[topic] += missed
            return missed

    def subscribed(self) -> None:
        """The cloud subscriptions were made anew: staleness counts from now, sequence numbers from the
        next message of each publisher."""
        with self.lock:
            self.start = time.monotonic()
            self.last_arrival = {SOURCE: None, TARGET: None}
            for sequences in self.sequences.values():
                sequences.clear()

    def lost_messages(self, topic: str, count: int) -> None:
        with self.lock:
            self.lost[topic] += count

    def event(self, name: str) -> None:
        with self.lock:
            self.events[name] += 1

    def pair_formed(self) -> None:
        with self.lock:
            self.paired += 1

    def drop(self, reason: str) -> None:
        with self.lock:
            self.dropped[reason] += 1

    def fail(self, reason: str) -> None:
        with self.lock:
            self.failed[reason] += 1
            self.last_outcome = f"failed: {reason}"

    def ok(self, latency: float, overhead: float, figures: dict[str, float], low_confidence: bool = False) -> None:
        with self.lock:
            self.registered += 1
            self.low_confidence += int(low_confidence)
            self.latency.append(latency)
            self.overhead.append(overhead)
            self.last = dict(figures)
            self.last_outcome = "registered with low confidence" if low_confidence else "registered"

    def snapshot(self) -> Snapshot:
        with self.lock:
            return Snapshot(
                Counter(self.received), Counter(self.dropped), Counter(self.failed), Counter(self.events),
                Counter(self.lost), Counter(self.missed), self.registered,
                self.low_confidence, self.paired, dict(self.last_arrival), list(self.latency),
                list(self.overhead), list(self.callback), dict(self.last), self.last_outcome, self.start)


@dataclass(frozen=True)
class Snapshot:
    """A consistent copy of `Stats` at one instant."""

    received: Counter
    dropped: Counter
    failed: Counter
    events: Counter
    lost: Counter
    missed: Counter
    registered: int
    low_confidence: int
    paired: int
    last_arrival: dict[str, float | None]
    latency: list[float]
    overhead: list[float]
    callback: list[float]
    last: dict[str, float]
    last_outcome: str
    start: float

    def silent_for(self, topic: str, now: float) -> float:
        """Seconds since `topic` last delivered a cloud (since start-up if it never did)."""
        return now - (self.last_arrival[topic] or self.start)


def build_status(s: Snapshot, now: float, name: str, hardware_id: str, stale_timeout: float,
                 warn_confidence: float, state: str = "active", fixed_target: bool = False,
                 notes: list[str] | None = None, localization: str = "") -> tuple[DiagnosticStatus, dict[str, str]]:
    """The node's DiagnosticStatus, and a note per stale topic ({"source": "no new source cloud for 3.1 s"}).

    `state` is the lifecycle state: topics are checked only when "active". `fixed_target` (a target file,
    or a latched target in latest_target mode): the target topic is not expected to update. `notes` are
    WARN reasons of the caller (e.g. a matched publisher that delivers nothing). `localization`: map mode's
    state (global, tracking, lost; "" when map mode is off); lost is a WARN."""
    level, stale = DiagnosticStatus.OK, {}
    notes = list(notes or [])
    if notes:
        level = DiagnosticStatus.WARN
    if state != "active":
        notes.append(f"lifecycle state {state}")
    for topic in (SOURCE, TARGET) if state == "active" else ():
        if topic == TARGET and fixed_target:
            continue
        silent = s.silent_for(topic, now)
        if silent > stale_timeout:
            level = DiagnosticStatus.WARN
            what = "no" if s.last_arrival[topic] is None else "no new"
            stale[topic] = f"{what} {topic} cloud for {silent:.1f} s"
            notes.append(stale[topic])
    if s.last_outcome.startswith("failed"):
        level = DiagnosticStatus.WARN
        notes.append(f"last registration {s.last_outcome}")
    elif s.last_outcome == "registered with low confidence":
        level = DiagnosticStatus.WARN
        notes.append(f"last registration has low confidence ({s.last.get('confidence', float('nan')):.2f} < "
                     f"warn_confidence {warn_confidence})")
    if localization == "lost" and state == "active":
        level = DiagnosticStatus.WARN
        notes.append("map mode: tracking lost (the next scan is localised without a guess)")
    dropped, failed = sum(s.dropped.values()), sum(s.failed.values())
    summary = f"registered {s.registered}, dropped {dropped}, failed {failed}"
    if lost := sum(s.lost.values()):
        summary += f", lost {lost} (by the middleware)"
    if missed := sum(s.missed.values()):
        summary += f", missed {missed} (sent, never received)"
    kv = {
        "state": state,
        "registered": s.registered,
        "low_confidence": s.low_confidence,
        "dropped": dropped,
        "failed": failed,
        "received.source": s.received[SOURCE],
        "received.target": s.received[TARGET],
        "lost.source": s.lost[SOURCE],  # lost by the middleware (QoS event message_lost): never received
        "lost.target": s.lost[TARGET],
        # sent but never received, by the publishers' sequence numbers (`Sequences`): includes those lost
        "missed.source": s.missed[SOURCE],
        "missed.target": s.missed[TARGET],
        "paired": s.paired,
        "light": s.events["light"],  # registered with the light settings under the latency budget (budget.latency)
        "time_jump": s.events["time_jump"],
        "reset": s.events["reset"],
        **({"localization": localization, "relocalize": s.events["relocalize"],
            "tracking_lost": s.events["tracking_lost"], "pose_jumps": s.events["pose_jumps"]} if localization else {}),
        "latency_ms.last": 1e3 * s.latency[-1] if s.latency else float("nan"),
        "latency_ms.median": _median_ms(s.latency),
        "latency_ms.p95": 1e3 * float(np.percentile(s.latency, 95)) if s.latency else float("nan"),
        "overhead_ms.median": _median_ms(s.overhead),
        "callback_ms.median": _median_ms(s.callback),
        **{f"dropped.{k}": n for k, n in sorted(s.dropped.items())},
        **{f"failed.{k}": n for k, n in sorted(s.failed.items())},
        **{f"last.{k}": x for k, x in s.last.items()},
    }
    status = DiagnosticStatus(level=level, name=f"{name}: registration", message="; ".join(notes + [summary]),
                              hardware_id=hardware_id, values=[KeyValue(key=k, value=_fmt(x)) for k, x in kv.items()])
    return status, stale


def _median_ms(values: list[float]) -> float:
    return 1e3 * float(np.median(values)) if values else float("nan")


def _fmt(x: Any) -> str:
    return f"{x:.4g}" if isinstance(x, float) else str(x)


class Reporter:
    """Counts drops (`dropped.<reason>`) and failures (`failed.<reason>`) in `stats` and logs a warning for each,
    at most one per reason every `WARN_THROTTLE_S` seconds. Thread-safe."""

    def __init__(self, stats: Stats, logger: Logger) -> None:
        self.stats = stats
        self.logger = logger
        self._warned: dict[str, float] = {}
        self._lock = threading.Lock()

    def drop(self, reason: str, text: str) -> None:
        self.stats.drop(reason)
        self.warn(reason, f"dropped ({reason}): {text}")

    def fail(self, reason: str, text: str) -> None:
        self.stats.fail(reason)
        self.warn(reason, f"failed ({reason}): {text}")

    def count(self, counter: str, reason: str, text: str) -> None:
        """`drop` (counter "dropped") or `fail` (counter "failed")."""
        (self.drop if counter == "dropped" else self.fail)(reason, text)

    def warn(self, key: str, text: str) -> None:
        """Log `text` as a warning unless one with this `key` was logged less than WARN_THROTTLE_S ago."""
        now = time.monotonic()
        with self._lock:
            if now - self._warned.get(key, -1e9) < WARN_THROTTLE_S:
                return
            self._warned[key] = now
        self.logger.warning(text)

    def info(self, text: str) -> None:
        self.logger.info(text)


@dataclass(frozen=True)
class Watched:
    """A cloud subscription whose silence is watched: its resolved topic name and reliability."""

    topic_name: str
    reliability: str


class InputWatch:
    """The silence of the cloud subscriptions: topics that stopped delivering (stale) and matched publishers
    whose clouds do not arrive. Each is logged once, with its likely cause. Called from one thread."""

    def __init__(self, publishers: Callable[[str], Sequence[TopicEndpointInfo]], logger: Logger) -> None:
        """`publishers(topic_name)`: the publishers matched on a topic (the node's get_publishers_info_by_topic)."""
        self._publishers = publishers
        self._logger = logger
        self._topics: dict[str, Watched] = {}
        self._matched_since: dict[str, float | None] = {}
        self._warned: dict[str, float | None] = {}  # topic -> its last arrival when it was warned about
        self._stale: set[str] = set()

    def watch(self, topics: dict[str, Watched]) -> None:
        """Watch these subscriptions (by topic: source, target) from now on; {}: none (inactive)."""
        self._topics = dict(topics)
        self._matched_since = {topic: None for topic in topics}
        self._warned.clear()
        self._stale.clear()

    def silent_publishers(self, snap: Snapshot, now: float, timeout: float, fixed_target: bool = False) -> list[str]:
        """Notes for watched topics with a matched publisher whose clouds have not arrived for `timeout` s: none
        since it appeared, or none since the last one (not for a fixed target). Each silence is also warned
        once, with the likely cause."""
        notes = []
        for topic, watched in self._topics.items():
            infos = self._publishers(watched.topic_name)
            last = snap.last_arrival[topic]
            if not infos:
                self._matched_since[topic] = None
                continue
            since = self._matched_since[topic] = self._matched_since[topic] or now
            silent = now - max(since, last or since)
            if silent <= timeout or (last is not None and topic == TARGET and fixed_target):
                continue
            kinds = sorted({i.qos_profile.reliability.name.lower() for i in infos})
            what = f"no {topic} cloud" if last is None else f"no new {topic} cloud (publisher stopped delivering)"
            note = f"{len(infos)} publisher(s) on {watched.topic_name} ({', '.join(kinds)}) but {what} for {silent:.1f} s"
            notes.append(note)
            if topic in self._warned and self._warned[topic] == last:
                continue  # warned about this silence already
            self._warned[topic] = last
            self._logger.warning(f"{note}: likely cause: {_silence_cause(topic, kinds, watched.reliability, last)}; "
                                 f"see {DOCS} (Large clouds)")
        return notes

    def warn_stale(self, stale: dict[str, str]) -> None:
        """Log each watched topic that has just become stale (`build_status`'s notes), once per staleness."""
        for topic, note in stale.items():
            if topic not in self._stale and topic in self._topics:
                self._logger.warning(f"{note} (topic {self._topics[topic].topic_name})")
        self._stale = set(stale)


def _silence_cause(topic: str, kinds: list[str], reliability: str, last: float | None) -> str:
    """The likely cause of a silent topic whose publishers offer `kinds` of reliability to a subscription of
    `reliability` (`last`: when its last cloud arrived, None: never)."""
    cause = ("large best-effort clouds are lost between processes without the shipped Fast DDS profile "
             "config/fastdds_large_clouds.xml in EVERY process (FASTDDS_DEFAULT_PROFILES_FILE), and clouds "
             "above its limit are lost even with it")
    if "best_effort" in kinds:
        cause += "; or publish the clouds with a reliable publisher (reliability reliable)"
        if reliability == "reliable":
            cause = ("a best-effort publisher does not match this node's reliable subscription "
                     f"({'qos.reliability' if topic == SOURCE else 'qos.target_reliability'}); " + cause)
    if last is not None:  # it delivered before
        stopped = "the publisher stopped publishing (driver stalled, bag ended)"
        cause = f"{stopped}, or its clouds grew: {cause}" if "best_effort" in kinds else stopped
    return cause
