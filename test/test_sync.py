"""Stamp pairing, the worker hand-over slot and the in-order outbox (pure Python, no DDS)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from genreg_ros.sync import Handover, PairSync

MS = 1_000_000  # ns


def test_pairs_within_slop_either_arrival_order():
    s = PairSync(slop=0.01, queue_size=5)
    assert s.add_source(100 * MS, "s0") == (None, [])
    pair, drops = s.add_target(105 * MS, "t0")
    assert (pair.source, pair.target, pair.source_stamp, pair.target_stamp) == ("s0", "t0", 100 * MS, 105 * MS)
    assert drops == [] and len(s) == 0
    assert s.add_target(200 * MS, "t1")[0] is None
    pair, _ = s.add_source(195 * MS, "s1")
    assert (pair.source, pair.target) == ("s1", "t1")


def test_nearest_candidate_wins_and_older_ones_are_dropped():
    s = PairSync(slop=0.05, queue_size=10)
    for i, t in enumerate((100, 120, 140)):
        s.add_target(t * MS, f"t{i}")
    pair, drops = s.add_source(138 * MS, "s")
    assert pair.target == "t2"
    assert sorted(d.stamp for d in drops) == [100 * MS, 120 * MS]
    assert {d.reason for d in drops} == {"unmatched"} and s.drops["unmatched"] == 2


def test_stamps_beyond_slop_are_dropped_once_the_other_topic_moves_on():
    s = PairSync(slop=0.05, queue_size=5)
    assert s.add_source(1000 * MS, "s") == (None, [])
    pair, drops = s.add_target(2000 * MS, "t")  # 1 s later: the source can never be paired
    assert pair is None
    assert [(d.topic, d.stamp, d.reason) for d in drops] == [("source", 1000 * MS, "unmatched")]
    # The next good pair still works; the lone target is dropped when sources move past it.
    assert s.add_source(3000 * MS, "s2")[0] is None
    pair, drops = s.add_target(3000 * MS, "t2")
    assert (pair.source, pair.target) == ("s2", "t2")
    assert s.drops == {"unmatched": 2}


def test_queue_is_bounded_and_evictions_are_counted():
    s = PairSync(slop=0.001, queue_size=3)
    dropped = []
    for i in range(10):  # sources only: nothing to pair with
        dropped += s.add_source(i * 100 * MS, i)[1]
    assert len(s) == 3
    assert [d.stamp for d in dropped] == [i * 100 * MS for i in range(7)]
    assert s.drops == {"queue_full": 7}


def test_latest_target_mode():
    s = PairSync(slop=0.0, queue_size=1, mode="latest_target")
    pair, drops = s.add_source(1 * MS, "s0")
    assert pair is None and [d.reason for d in drops] == ["no_target"]
    s.add_target(5 * MS, "ref1")
    assert s.add_source(900 * MS, "s1")[0].target == "ref1"  # far in time: slop does not apply
    assert s.add_source(901 * MS, "s2")[0].target == "ref1"  # the reference is reused
    s.add_target(10 * MS, "ref2")
    assert s.add_source(902 * MS, "s3")[0].target == "ref2"
    assert s.drops == {"no_target": 1} and len(s) == 1


def test_invalid_settings():
    with pytest.raises(ValueError):
        PairSync(0.1, 5, mode="exact")
    with pytest.raises(ValueError):
        PairSync(-0.1, 5)
    with pytest.raises(ValueError):
        PairSync(0.1, 0)


@pytest.mark.parametrize("seed", range(5))
def test_random_streams_pair_correctly_and_account_for_every_message(seed):
    """10 Hz source and target with stamp jitter, 10 % losses and delivery delays that interleave the topics."""
    rng = np.random.default_rng(seed)
    slop, qsize = 0.02, 4
    s = PairSync(slop=slop, queue_size=qsize)
    arrivals = []  # (arrival time, topic, stamp, tick)
    for topic in ("source", "target"):
        for k in range(300):
            if rng.uniform() < 0.9:
                stamp = k * 100 * MS + int(rng.normal(0, 3 * MS))
                arrivals.append((stamp + int(rng.uniform(0, 40 * MS)), topic, stamp, k))
    arrivals.sort()
    pairs, dropped = [], 0
    for _, topic, stamp, k in arrivals:
        add = s.add_source if topic == "source" else s.add_target
        pair, drops = add(stamp, (topic, k))
        dropped += len(drops)
        assert len(s) <= 2 * qsize
        if pair:
            pairs.append(pair)
            assert abs(pair.source_stamp - pair.target_stamp) <= slop * 1e9
            assert pair.source[0] == "source" and pair.target[0] == "target"
    used = [p.source for p in pairs] + [p.target for p in pairs]
    assert len(used) == len(set(used))  # no message is used twice
    assert 2 * len(pairs) + dropped + len(s) == len(arrivals)  # every message is paired, dropped or held
    both = {k for _, t, _, k in arrivals if t == "source"} & {k for _, t, _, k in arrivals if t == "target"}
    assert all(p.source[1] == p.target[1] for p in pairs)  # each with its own partner
    assert len(pairs) >= 0.9 * len(both)  # and nearly every tick with both messages is paired


def test_handover_replaces_a_waiting_item_and_numbers_every_item_that_leaves():
    slot = Handover()
    assert slot.put("a") is None
    assert slot.put("b") == ("a", 0)  # replaced: it leaves first, with the first ticket
    assert slot.take(timeout=0.1) == ("b", 1)
    t0 = time.monotonic()
    assert slot.take(timeout=0.1) is None
    assert time.monotonic() - t0 >= 0.09
    slot.put("c")
    assert slot.clear() == ("c", 2) and slot.clear() is None
    got: list = []
    reader = threading.Thread(target=lambda: got.extend(iter(slot.outbox.get, None)))
    reader.start()
    slot.outbox.done(2, "c discarded", wait=False)
    slot.outbox.done(0, "a superseded", wait=False)
    slot.outbox.done(1, "b registered")
    slot.outbox.close()
    reader.join(timeout=2)
    assert got == ["a superseded", "b registered", "c discarded"]  # in the order they left the slot


def test_handover_wakes_a_worker_and_close_unblocks():
    slot, got = Handover(), []

    def worker():
        while not slot.closed:
            taken = slot.take(timeout=5.0)
            if taken is not None:
                got.append(taken)

    th = threading.Thread(target=worker)
    th.start()
    slot.put(1)
    deadline = time.monotonic() + 2
    while not got and time.monotonic() < deadline:
        time.sleep(0.01)
    slot.close()
    th.join(timeout=2)
    assert got == [(1, 0)] and not th.is_alive()


def test_in_order_hands_results_on_in_ticket_order_and_skips_nones():
    from genreg_ros.sync import InOrder

    box = InOrder(limit=2)
    tickets = [box.ticket() for _ in range(4)]
    assert tickets == [0, 1, 2, 3]
    got: list = []
    reader = threading.Thread(target=lambda: got.extend(iter(box.get, None)))
    reader.start()
    box.done(2, "c")  # finished early: waits for 0 and 1
    box.done(1, None)  # a dropped pair: nothing to publish
    time.sleep(0.05)
    assert got == []
    box.done(0, "a")
    box.done(3, "d")
    time.sleep(0.05)
    box.close()
    reader.join(timeout=2)
    assert got == ["a", "c", "d"] and not reader.is_alive()


def test_in_order_done_waits_beyond_its_limit_except_for_the_next_ticket():
    from genreg_ros.sync import InOrder

    box = InOrder(limit=1)
    t0, t1, t2 = box.ticket(), box.ticket(), box.ticket()
    box.done(t1, "b")  # one waiting: the limit
    finished = threading.Event()
    late = threading.Thread(target=lambda: (box.done(t2, "c"), finished.set()))
    late.start()
    time.sleep(0.05)
    assert not finished.is_set()  # t2 waits for room
    box.done(t0, "a")  # the ticket the consumer needs next never waits
    assert [box.get(), box.get()] == ["a", "b"]
    assert finished.wait(2) and box.get() == "c"
    late.join()
    t3, t4 = box.ticket(), box.ticket()
    box.done(t4, "e", wait=False)  # a caller that must not block (a superseded pair's status): beyond the limit
    box.done(t3, "d")
    assert [box.get(), box.get()] == ["d", "e"]
