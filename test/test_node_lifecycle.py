"""register_node as a lifecycle node, driven through its lifecycle services by a client of this test's own
(the node in its own process, autostart false), with a latched (transient_local) target that was
published before the node started; and a fixed target read from a file (in-process node).
"""

from __future__ import annotations

import time

import numpy as np
import pytest
import rclpy
from lifecycle_msgs.msg import State, Transition
from lifecycle_msgs.srv import ChangeState, GetState
from rclpy.parameter import Parameter
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from test_node import (
    SHIPPED_MODEL,
    SMALL_T,
    TEST_PARAMS,
    check_outputs,
    diag_values,
    make_pair,
    node_process,
    redkitchen_pair,
    running_node,
)

from genreg_core.data.rgbd import RGBDSequence
from genreg_ros.node import RegisterNode, StartupError


def change(h, transition_id: int) -> bool:
    return h.call(ChangeState, "change_state", ChangeState.Request(transition=Transition(id=transition_id))).success


def state(h) -> int:
    return h.call(GetState, "get_state").current_state.id


@pytest.fixture(scope="module")
def managed(ros_namespace, tmp_path_factory):
    """The node (autostart false, latest_target, transient_local target) and a latched target published
    before it starts."""
    latched = {}

    def publish_latched_target(h):
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        pub = h.helper.create_publisher(PointCloud2, "target_cloud", qos)
        tgt = make_pair(SMALL_T, 100.0)[1]
        pub.publish(tgt)
        latched.update(pub=pub, target=tgt)

    params = {**TEST_PARAMS, "model.checkpoint": SHIPPED_MODEL, "autostart": "false",
              "sync.mode": "latest_target", "qos.target_durability": "transient_local",
              "qos.reliability": "reliable", "diagnostics.stale_timeout": 0.5}
    log = tmp_path_factory.mktemp("lifecycle") / "node.log"
    with node_process(f"{ros_namespace}/lifecycle", log, params, before=publish_latched_target) as (h, proc, path):
        yield h, proc, path


def test_transitions_through_the_lifecycle_services_with_a_latched_target(managed):
    h, proc, log = managed
    assert state(h) == State.PRIMARY_STATE_UNCONFIGURED
    assert diag_values(h.status(after=time.monotonic()))["state"] == "unconfigured"
    assert change(h, Transition.TRANSITION_CONFIGURE) and state(h) == State.PRIMARY_STATE_INACTIVE
    assert h.pub_source.get_subscription_count() == 0  # inactive: not subscribed
    assert change(h, Transition.TRANSITION_ACTIVATE) and state(h) == State.PRIMARY_STATE_ACTIVE
    deadline = time.monotonic() + 10
    while h.pub_source.get_subscription_count() == 0:
        assert time.monotonic() < deadline
        time.sleep(0.05)
    time.sleep(0.5)
    # The target was published once, before the node existed: transient_local delivers it.
    for t in (200.0, 201.0):
        src, _, rec = make_pair(SMALL_T, t, seed=int(t))
        h.pub_source.publish(src)
        check_outputs(*h.wait_output(src.header, timeout=20.0), rec, src.header, SMALL_T)
    time.sleep(1.0)  # longer than the stale timeout: a latched target is not "stale"
    s = h.status(after=time.monotonic())
    assert "target cloud" not in s.message, s.message
    v = diag_values(s)
    assert v["received.target"] == "1" and v["registered"] == "2" and v["state"] == "active"
    # reset keeps the latched target (latest_target) and clears the rest
    assert h.call(Trigger, "reset").success
    src, _, rec = make_pair(SMALL_T, 202.0, seed=3)
    h.pub_source.publish(src)
    check_outputs(*h.wait_output(src.header, timeout=20.0), rec, src.header, SMALL_T)
    # deactivate: no subscriptions and no outputs
    assert change(h, Transition.TRANSITION_DEACTIVATE) and state(h) == State.PRIMARY_STATE_INACTIVE
    n = len(h.aligned)
    src, _, _ = make_pair(SMALL_T, 203.0)
    h.pub_source.publish(src)
    time.sleep(1.0)
    assert len(h.aligned) == n
    assert change(h, Transition.TRANSITION_CLEANUP) and state(h) == State.PRIMARY_STATE_UNCONFIGURED
    assert change(h, Transition.TRANSITION_UNCONFIGURED_SHUTDOWN)
    assert proc.wait(timeout=20) == 0  # finalized: the process exits on its own
    assert "Traceback" not in log.read_text()


def test_a_target_file_is_the_fixed_target_and_target_crop_radius_is_refused(ros_namespace, tmp_path,
                                                                             untrained_checkpoint):
    """A fixed target from a PLY file (redkitchen frame 800): frame 801 registers against it, the target topic
    is not subscribed and the target is never stale. target_crop_radius is gone (map mode is the one way to
    localise in a large map): a node given it stops at start-up with one line saying so."""
    import open3d as o3d

    seq = RGBDSequence.redkitchen()
    tgt = seq.points(800, 8).astype(np.float64)
    path = tmp_path / "target.ply"
    assert o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt)))
    src, _, rec, T_true = redkitchen_pair(801, 800, 300.0)
    with running_node(f"{ros_namespace}/target_file", SHIPPED_MODEL, target_file=str(path), target_frame="map") as h:
        assert h.pub_target.get_subscription_count() == 0  # the topic is not subscribed
        h.pub_source.publish(src)
        aligned, tf = h.wait_output(src.header, timeout=30.0)
        check_outputs(aligned, tf, rec, src.header, T_true, src_frame="camera", tgt_frame="map", rot_tol=0.6,
                      trans_tol=0.01)
        time.sleep(0.5)
        assert 0 < float(h.counters()["last.points_target"]) <= len(tgt)
        s = h.status(after=time.monotonic())
        assert "target cloud" not in s.message, s.message  # a fixed target is never stale
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        overrides = [Parameter("model.checkpoint", value=str(untrained_checkpoint)), Parameter("target_file", value=str(path)),
                     Parameter("target_frame", value="map"), Parameter("target_crop_radius", value=4.0)]
        with pytest.raises(StartupError, match=r"unknown parameter 'target_crop_radius' \(removed: use map.enabled") as error:
            RegisterNode(context=ctx, namespace=f"{ros_namespace}/crop", parameter_overrides=overrides)
        assert "\n" not in str(error.value)
    finally:
        rclpy.shutdown(context=ctx)
