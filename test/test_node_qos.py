"""The target subscription's QoS settings cannot contradict each other: a transient_local target
subscription is reliable (`QosParams.target_reliability_resolved`), so it receives a cloud latched before
the node started; best_effort with transient_local is refused at start-up with one line.

The node test runs the node in this process with the object model, small synthetic clouds and only
`sync.mode: latest_target` and `qos.target_durability: transient_local` changed from the defaults besides
test_node's fast settings (`qos.reliability` stays best_effort, `qos.target_reliability` same).
"""

from __future__ import annotations

import pytest
import rclpy
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from test_node import (
    SMALL_T,
    SRC_FRAME,
    TEST_PARAMS,
    TGT_FRAME,
    Harness,
    diag_values,
    make_pair,
    wait_subscribed,
)

from genreg_core.config import OBJECT_MODEL
from genreg_core.errors import ConfigError
from genreg_ros.config import QosParams
from genreg_ros.node import RegisterNode, StartupError, main

LATCHED = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)


@pytest.fixture
def ns(ros_namespace, request) -> str:
    return f"{ros_namespace}/qos_{request.node.name.split('[')[0][5:]}"


def test_a_transient_local_target_is_reliable_unless_named_otherwise():
    assert QosParams().target_reliability_resolved == "best_effort"  # same: the source's
    assert QosParams(reliability="reliable").target_reliability_resolved == "reliable"
    latched = QosParams(target_durability="transient_local")
    assert (latched.reliability, latched.target_reliability) == ("best_effort", "same")
    assert latched.target_reliability_resolved == "reliable"
    assert QosParams(target_reliability="best_effort").target_reliability_resolved == "best_effort"
    assert QosParams(target_durability="transient_local", target_reliability="reliable"
                     ).target_reliability_resolved == "reliable"


def test_best_effort_with_transient_local_is_refused_with_one_line(ns, tmp_path, capsys):
    with pytest.raises(ConfigError, match="qos.target_reliability best_effort cannot receive a latched target"):
        QosParams(target_durability="transient_local", target_reliability="best_effort")
    path = tmp_path / "latched.yaml"
    path.write_text("/**:\n  ros__parameters:\n    qos:\n      target_durability: transient_local\n"
                    "      target_reliability: best_effort\n")
    assert main(["register_node", "--ros-args", "--params-file", str(path)]) == 1  # the exit code
    err = capsys.readouterr().err
    assert err.startswith("register_node: error: params file") and err.count("\n") == 1, err
    assert "qos.target_reliability best_effort cannot receive a latched target" in err
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:  # the same as parameters (-p): the node's start-up error, one line
        overrides = [Parameter("qos.target_durability", value="transient_local"),
                     Parameter("qos.target_reliability", value="best_effort")]
        with pytest.raises(StartupError, match="use reliable or same") as error:
            RegisterNode(context=ctx, namespace=ns, parameter_overrides=overrides)
        assert "\n" not in str(error.value)
    finally:
        rclpy.shutdown(context=ctx)


def test_a_target_latched_before_the_node_started_is_registered_with_same_reliability(ns):
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    server = rclpy.create_node("genreg_test_map_server", namespace=ns, context=ctx)
    h = None
    try:
        source, target, records = make_pair(SMALL_T, 100.0, n=2000)
        latched = server.create_publisher(PointCloud2, "target_cloud", LATCHED)
        latched.publish(target)  # before the node exists: only a reliable transient_local subscription gets it
        values = {**TEST_PARAMS, "model.checkpoint": OBJECT_MODEL, "sync.mode": "latest_target",
                  "qos.target_durability": "transient_local"}
        node = RegisterNode(context=ctx, namespace=ns, parameter_overrides=[Parameter(k, value=v)
                                                                            for k, v in values.items()])
        assert node.config.qos.target_reliability == "same" and node.config.qos.reliability == "best_effort"
        assert node._subs["target"].qos_profile.reliability == ReliabilityPolicy.RELIABLE  # what it subscribes with
        h = Harness(ctx, ns, node)
        h.wait(lambda: any(diag_values(s).get("received.target") == "1" for m in h.diagnostics for s in m.status),
               20.0, "the latched target received")
        wait_subscribed(h, h.pub_source)
        h.pub_source.publish(source)
        aligned, tf = h.wait_output(source.header, timeout=30.0)  # registered against the latched target
        assert (tf.header.frame_id, tf.child_frame_id) == (TGT_FRAME, SRC_FRAME) and tf.header.stamp == source.header.stamp
        assert aligned.width * aligned.height == len(records)
        status = diag_values(h.result_for(source.header))
        assert status["published"] == "true" and status["target_frame"] == TGT_FRAME, status
    finally:
        if h is not None:
            h.close()
        server.destroy_node()
        rclpy.shutdown(context=ctx)
