"""Pairing of source and target clouds by header stamp, plus the one-slot hand-over to the worker.

Pure Python (no rclpy): stamps are integer nanoseconds, items are opaque. Not thread-safe; the node
calls it under its own lock.

Policies (`PairSync.mode`):
- "approximate": a message is paired on arrival with the queued message of the other topic whose
  stamp is nearest, if within `slop`. Greedy, so the lowest latency wins over a possibly better later
  match. Each topic keeps at most `queue_size` unpaired messages. Messages that can no longer be
  paired are dropped and counted; per topic, stamps are assumed to increase.
- "latest_target": each source is paired at once with the most recent target (a fixed or slowly
  changing reference); `slop` is not used. Sources before the first target are dropped.

Drop reasons: 'queue_full' (evicted, oldest first), 'unmatched' (the other topic has moved past
stamp + slop, or a newer pair was made), 'no_target' (latest_target mode, no target yet).

`Handover` passes the pairs on to the workers (a newer pair replaces a waiting one) and numbers every pair
that leaves it, so that `InOrder` hands the publications on in that order.
"""

from __future__ import annotations

import bisect
import threading
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

MODES = ("approximate", "latest_target")
SOURCE, TARGET = "source", "target"
S = TypeVar("S")
T = TypeVar("T")


@dataclass(frozen=True)
class Pair(Generic[S, T]):
    """A source and a target message to register, with their stamps in nanoseconds."""

    source: S
    target: T
    source_stamp: int
    target_stamp: int


@dataclass(frozen=True)
class Drop:
    """One dropped message: which topic, its stamp and why."""

    topic: str
    stamp: int
    reason: str


@dataclass
class _Entry:
    stamp: int
    item: Any


class PairSync:
    """Approximate-time (or latest-target) pairing with bounded queues and counted drops."""

    def __init__(self, slop: float, queue_size: int, mode: str = "approximate") -> None:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
        if slop < 0 or queue_size < 1:
            raise ValueError("slop must be >= 0 and queue_size >= 1")
        self.slop_ns = round(slop * 1e9)
        self.queue_size = int(queue_size)
        self.mode = mode
        self._queues: dict[str, deque[_Entry]] = {SOURCE: deque(), TARGET: deque()}
        self._newest: dict[str, int | None] = {SOURCE: None, TARGET: None}
        self._latest_target: _Entry | None = None
        self.drops: Counter[str] = Counter()  # reason -> count, over both topics

    def __len__(self) -> int:
        """Messages held (queued, plus the latest target in latest_target mode)."""
        return sum(len(q) for q in self._queues.values()) + (self._latest_target is not None)

    def add_source(self, stamp: int, item: Any) -> tuple[Pair | None, list[Drop]]:
        """Offer a source message; returns the pair it completed (if any) and the messages dropped."""
        if self.mode == "latest_target":
            target = self._latest_target
            if target is None:
                return None, self._count([Drop(SOURCE, stamp, "no_target")])
            return Pair(item, target.item, stamp, target.stamp), []
        return self._add(SOURCE, stamp, item)

    def add_target(self, stamp: int, item: Any) -> tuple[Pair | None, list[Drop]]:
        """Offer a target message; see `add_source`."""
        if self.mode == "latest_target":
            self._latest_target = _Entry(stamp, item)
            return None, []
        return self._add(TARGET, stamp, item)

    @property
    def latest_target(self) -> Any:
        """The target every source is paired with (latest_target mode; None: none yet, or approximate mode)."""
        return None if self._latest_target is None else self._latest_target.item

    def carry_latest_target(self, other: PairSync) -> None:
        """Keep `other`'s latest target when both pair with the latest target (new settings, same reference)."""
        if self.mode == other.mode == "latest_target" and other._latest_target is not None:
            self._latest_target = self._latest_target or other._latest_target

    def clear(self, keep_latest_target: bool = False) -> None:
        """Forget every held message and the newest stamps seen (not counted as drops); in latest_target
        mode the reference target stays if `keep_latest_target`."""
        for q in self._queues.values():
            q.clear()
        self._newest = {SOURCE: None, TARGET: None}
        if not keep_latest_target:
            self._latest_target = None

    def _add(self, topic: str, stamp: int, item: Any) -> tuple[Pair | None, list[Drop]]:
        other = TARGET if topic == SOURCE else SOURCE
        own_q, other_q = self._queues[topic], self._queues[other]
        self._newest[topic] = stamp if self._newest[topic] is None else max(self._newest[topic], stamp)
        drops: list[Drop] = []
        best = min(other_q, key=lambda e: abs(e.stamp - stamp), default=None)
        if best is not None and abs(best.stamp - stamp) <= self.slop_ns:
            # Everything older than the two paired messages can no longer be paired in order.
            drops += self._pop_older(other, other_q, best.stamp, inclusive=True, keep=best)
            drops += self._pop_older(topic, own_q, stamp, inclusive=False)
            other_q.remove(best)
            pair = Pair(item, best.item, stamp, best.stamp) if topic == SOURCE else Pair(
                best.item, item, best.stamp, stamp
            )
            return pair, self._count(drops)
        bisect.insort(own_q, _Entry(stamp, item), key=lambda e: e.stamp)
        while len(own_q) > self.queue_size:
            drops.append(Drop(topic, own_q.popleft().stamp, "queue_full"))
        for name, q in self._queues.items():
            newest_other = self._newest[TARGET if name == SOURCE else SOURCE]
            if newest_other is not None:
                drops += self._pop_older(name, q, newest_other - self.slop_ns, inclusive=False)
        return None, self._count(drops)

    @staticmethod
    def _pop_older(topic: str, q: deque[_Entry], limit: int, inclusive: bool, keep: Any = None) -> list[Drop]:
        """Remove entries with stamp < limit (<= if inclusive), except `keep`, as 'unmatched' drops."""
        gone = [e for e in q if e is not keep and (e.stamp < limit or (inclusive and e.stamp == limit))]
        for e in gone:
            q.remove(e)
        return [Drop(topic, e.stamp, "unmatched") for e in gone]

    def _count(self, drops: list[Drop]) -> list[Drop]:
        self.drops.update(d.reason for d in drops)
        return drops


class Handover:
    """The one waiting pair between the subscription callbacks and the workers, and its place in the order of
    publication.

    A newer pair replaces a waiting one (`put` returns the one it replaced). Every pair that leaves the slot,
    taken by a worker (`take`), replaced (`put`) or discarded (`clear`), leaves with a ticket of `outbox`, drawn
    under the slot's lock: tickets follow the order the pairs left in, and `outbox` hands the publications on
    in that order. Memory stays bounded (one waiting pair) and latency stays one registration at most.
    Thread-safe.
    """

    def __init__(self, workers: int = 1) -> None:
        self._cond = threading.Condition()
        self._item: Any = None
        self._closed = False
        self.outbox = InOrder(limit=workers)

    def put(self, item: Any) -> tuple[Any, int] | None:
        """Hand over `item`; the waiting item it replaced and that item's ticket (None if the slot was empty)."""
        with self._cond:
            replaced, self._item = self._item, item
            self._cond.notify()
            return None if replaced is None else (replaced, self.outbox.ticket())

    def take(self, timeout: float | None = None) -> tuple[Any, int] | None:
        """Wait for an item and remove it: the item and its ticket; None on timeout or after `close()`."""
        with self._cond:
            if self._item is None and not self._closed:
                self._cond.wait(timeout)
            item, self._item = self._item, None
            return None if item is None else (item, self.outbox.ticket())

    def clear(self) -> tuple[Any, int] | None:
        """Remove the waiting item without waiting: it and its ticket (None if the slot was empty)."""
        with self._cond:
            item, self._item = self._item, None
            return None if item is None else (item, self.outbox.ticket())

    def close(self) -> None:
        """Wake every waiting `take` for shutdown (the outbox is closed on its own, after the workers)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def closed(self) -> bool:
        return self._closed


class InOrder:
    """Results handed from several workers to one consumer in the order their work was taken.

    A worker takes a `ticket()` when it takes its work and hands its result (None: nothing to hand on)
    with `done(ticket, item)`; `get()` returns the items in ticket order, skipping the Nones, so a pair
    that finished early waits for the one taken before it. At most `limit` finished items wait: `done`
    blocks beyond that, except for the ticket the consumer needs next and for small items handed over with
    `wait=False` (a caller that must not block). Thread-safe.
    """

    def __init__(self, limit: int = 1) -> None:
        self._cond = threading.Condition()
        self._limit = limit
        self._issued = 0
        self._next = 0
        self._done: dict[int, Any] = {}
        self._closed = False

    def ticket(self) -> int:
        with self._cond:
            self._issued += 1
            return self._issued - 1

    def done(self, ticket: int, item: Any, wait: bool = True) -> None:
        with self._cond:
            while wait and len(self._done) >= self._limit and ticket != self._next and not self._closed:
                self._cond.wait()
            self._done[ticket] = item
            self._cond.notify_all()

    def get(self) -> Any:
        """The next item in ticket order (waits for it); None once closed and nothing more is ready."""
        with self._cond:
            while True:
                while self._next in self._done:
                    item = self._done.pop(self._next)
                    self._next += 1
                    self._cond.notify_all()
                    if item is not None:
                        return item
                if self._closed:
                    return None
                self._cond.wait()

    def close(self) -> None:
        """Let `get` return None once the finished items are handed out (a ticket never done is not waited for)."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()
