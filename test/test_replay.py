"""Replay harness against a real register_node in a subprocess, real DDS on loopback.

Model: the shipped scene model `7scenes` with config/genreg.yaml (point-to-point ICP on, seed 0, so runs
repeat). Thresholds, from measured runs of this setup on redkitchen frames 800-815 at pixel stride 8,
gap 1 (15 pairs): RE mean 0.20 / max 0.38 deg and TE mean 4.2 / max 9.2 mm (Open3D ICP on the same
pairs: 0.45 deg, 13 mm). No motion (identity) scores RE mean 0.52 deg here, and an inverted transform
would double the motion. So we require RE mean < 0.35 deg, RE max < 0.8 deg, TE mean < 8 mm and TE max
< 20 mm.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest

from genreg_core.data.rgbd import RGBDSequence
from genreg_ros.bag import BagWriter, cloud_message, read_bag, sequence_frames, write_sequence_bag
from genreg_ros.bag.writer import TYPESTORE
from genreg_ros.replay.cli import main as replay_main
from genreg_ros.replay.harness import NodeProcess, ReplayOptions, replay, restamp, ros_env
from genreg_ros.replay.scoring import PairResult, assign_reasons

RE_MEAN_DEG, RE_MAX_DEG = 0.35, 0.8
TE_MEAN_M, TE_MAX_M = 0.008, 0.020
PIXEL_STRIDE = 8  # ~4k points per cloud: quick to send, decode and register
SHIPPED_MODEL = "7scenes"


def test_restamp_rewrites_only_the_header_stamp():
    msg = cloud_message(1_000_000_123, "cam", np.zeros((4, 3), np.float32))
    raw = bytes(TYPESTORE.serialize_cdr(msg, "sensor_msgs/msg/PointCloud2"))
    back = TYPESTORE.deserialize_cdr(restamp(raw, 7_500_000_001), "sensor_msgs/msg/PointCloud2")
    assert (back.header.stamp.sec, back.header.stamp.nanosec) == (7, 500_000_001)
    assert back.header.frame_id == "cam" and back.width == 4 and len(restamp(raw, 1)) == len(raw)


def test_missing_checkpoint_is_one_error_line(tmp_path, capsys):
    assert replay_main(["--bag", str(tmp_path), "--checkpoint", str(tmp_path / "missing.pt"), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("genreg-replay: error: checkpoint not found"), err


def test_reasons_consume_node_counters():
    def pair(k: int, malformed: str = "") -> PairResult:
        return PairResult("b", k, k, k - 1, k, k - 1, "c", "c", 10, np.eye(4), malformed=malformed)

    pairs = [pair(1, "source: truncated_data"), pair(2, "target: truncated_data"), pair(3), pair(4), pair(5)]
    assign_reasons(pairs, {"dropped.truncated_data": 1, "dropped.superseded": 1, "failed.too_few_points": 1,
                            "received.source": 5})
    assert [p.reason for p in pairs] == [
        "malformed source (truncated_data)", "malformed target (truncated_data), not counted by the node",
        "node dropped.superseded", "node failed.too_few_points", "lost (no output, not counted by the node)"]


@pytest.fixture(scope="module")
def bags(tmp_path_factory) -> dict[str, object]:
    """A short redkitchen bag (16 frames) and a bag with malformed clouds in it (10 frames)."""
    root = tmp_path_factory.mktemp("bags")
    seq = RGBDSequence.redkitchen()
    write_sequence_bag(seq, root / "good", range(800, 816), pixel_stride=PIXEL_STRIDE)
    with BagWriter(root / "bad") as writer:
        writer.set_info({"sequence": "redkitchen", "frames": list(range(820, 830))})
        for k, frame in enumerate(sequence_frames(seq, range(820, 830), PIXEL_STRIDE, start_ns=2 * 10**18)):
            msg = cloud_message(frame.stamp_ns, writer.frame_id, frame.points, frame.colors)
            if k == 3:
                msg = dataclasses.replace(msg, data=msg.data[: len(msg.data) // 2])  # truncated data
            elif k == 6:
                fields = [dataclasses.replace(f, name=n) for f, n in zip(msg.fields, ("a", "b", "c", "rgb"))]
                msg = dataclasses.replace(msg, fields=fields)  # wrong fields: no x/y/z
            writer.write_cloud(msg)
            writer.write_pose(frame.stamp_ns, frame.pose)
    return {"good": root / "good", "bad": root / "bad"}


@pytest.fixture(scope="module")
def node(ros_namespace, tmp_path_factory):
    """register_node with config/genreg.yaml and the shipped scene model, shared by the replays below."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in ros_env().items():  # Fast DDS profile etc. for this process and the node
            mp.setenv(key, value)
        options = ReplayOptions(namespace=ros_namespace, checkpoint=SHIPPED_MODEL)
        proc = NodeProcess(options, tmp_path_factory.mktemp("node") / "register_node.log")
        yield proc
        alive = proc.alive()
        code = proc.stop()
        assert alive, f"register_node died: {proc.error_line()}"
        assert code == 0, f"register_node exit code {code}: {proc.error_line()}"


def _options(ns: str, **kw) -> ReplayOptions:
    return ReplayOptions(namespace=ns, connect=True, startup_timeout=90.0, verbose=False, **kw)


def test_replay_gap1_lockstep_accuracy_stamps_frames(node, bags, ros_namespace, tmp_path):
    result = replay([bags["good"]], _options(ros_namespace, gap=1, lockstep=True, report_dir=tmp_path))
    s, pairs = result.summary, result.pairs
    assert s["pairs"] == 15 and s["registered"] == 15, s["reasons"]
    for p in pairs:  # every output: the source's (published) stamp, parent = target frame, child = source frame
        assert not p.header_problems, p.header_problems
        assert p.target_frame == p.source_frame - 1 and p.latency is not None and p.latency > 0
    assert s["re"]["mean"] < RE_MEAN_DEG and s["re"]["max"] < RE_MAX_DEG, s["re"]
    assert s["te"]["mean"] < TE_MEAN_M and s["te"]["max"] < TE_MAX_M, s["te"]
    assert s["icp_re"]["n"] == 15  # the ICP baseline ran on the same pairs
    assert (tmp_path / "report.md").is_file() and (tmp_path / "errors.png").is_file()
    assert (tmp_path / "trajectory.png").is_file()
    assert "RE mean / median" in result.text and "15 registered" in result.text


def test_replay_original_timing_every_pair_accounted(node, bags, ros_namespace):
    result = replay([bags["good"]], _options(ros_namespace, gap=1, rate=1.0, icp=False))
    s = result.summary
    assert s["pairs"] == 15 and s["registered"] >= 1
    missing = [p for p in result.pairs if not p.registered]
    assert all(p.reason.startswith("node ") for p in missing), [p.reason for p in missing]
    assert s["lost"] == 0 and s["header_problems"] == 0
    assert sum(s["reasons"].values()) == s["missing"]


def test_replay_malformed_bag_node_survives(node, bags, ros_namespace):
    bag = read_bag(bags["bad"])
    assert [c.error for c in bag.clouds if c.error] == ["truncated_data", "missing_xyz"]
    t0 = time.monotonic()
    result = replay([bags["bad"]], _options(ros_namespace, gap=1, lockstep=True, icp=False))
    s = result.summary
    assert node.alive()
    reasons = {p.k: p.reason for p in result.pairs if not p.registered}
    assert reasons == {3: "malformed source (truncated_data)", 4: "malformed target (truncated_data)",
                       6: "malformed source (missing_xyz)", 7: "malformed target (missing_xyz)"}
    assert s["registered"] == 5 and all(p.registered for p in result.pairs if p.k in (5, 8, 9))
    assert s["node_counts"]["dropped.truncated_data"] == 2 and s["node_counts"]["dropped.missing_xyz"] == 2
    assert [m["frame"] for m in s["malformed"]] == [823, 826]
    assert "malformed in bag   2 clouds" in result.text
    assert time.monotonic() - t0 < 60
