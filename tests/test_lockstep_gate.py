"""The lockstep gate decides what a service processes at each tick, independent of arrival timing."""
from services.runtime.lockstep import LockstepGate

UP = {"classifier"}


def make_gate():
    gate = LockstepGate(("classifier",), wants=lambda key: key.startswith("falconry/uav1/"))
    gate.first_tick = False
    return gate


def test_waits_for_upstream_ack_and_named_messages():
    gate = make_gate()
    gate.begin(5, {"falconry/uav1/odometry": 7})
    assert "ack of classifier" in gate.missing(UP)
    gate.record_ack("classifier", 5, {"falconry/uav1/detections": 3})
    assert set(gate.missing(UP)) == {"falconry/uav1/odometry#7", "falconry/uav1/detections#3"}
    gate.hold("falconry/uav1/odometry", 7, "odo7")
    gate.hold("falconry/uav1/detections", 3, "det3")
    assert gate.missing(UP) == []
    assert [item for _, item in gate.release(UP)] == ["det3", "odo7"]


def test_messages_beyond_the_bound_wait_for_a_later_tick():
    gate = make_gate()
    gate.begin(1, {"falconry/uav1/map": 2})
    for seq in (1, 2, 3):
        gate.hold("falconry/uav1/map", seq, f"map{seq}")
    gate.record_ack("classifier", 1, {})
    assert [item for _, item in gate.release(UP)] == ["map1", "map2"]
    gate.begin(2, {"falconry/uav1/map": 3})
    gate.record_ack("classifier", 2, {})
    assert gate.missing(UP) == []
    assert [item for _, item in gate.release(UP)] == ["map3"]


def test_dead_upstream_is_not_waited_for_and_unknown_publishers_pass():
    gate = make_gate()
    gate.begin(1, {})
    gate.hold("falconry/uav1/extra", 99, "x")
    assert gate.missing(set()) == []
    assert [item for _, item in gate.release(set())] == ["x"]


def test_restarted_publisher_counting_from_one_again_is_released():
    gate = make_gate()
    gate.begin(1, {"falconry/uav1/map": 50})
    gate.hold("falconry/uav1/map", 50, "old")
    gate.record_ack("classifier", 1, {})
    assert [i for _, i in gate.release(UP)] == ["old"]
    gate.begin(2, {"falconry/uav1/map": 2})
    gate.hold("falconry/uav1/map", 1, "new1")
    gate.hold("falconry/uav1/map", 2, "new2")
    gate.record_ack("classifier", 2, {})
    assert gate.missing(UP) == []
    assert [i for _, i in gate.release(UP)] == ["new1", "new2"]


def test_release_order_is_by_key_not_arrival():
    gate = make_gate()
    gate.begin(1, {})
    gate.record_ack("classifier", 1, {})
    gate.hold("falconry/uav1/b", 1, "b")
    gate.hold("falconry/uav1/a", 1, "a")
    assert [i for _, i in gate.release(UP)] == ["a", "b"]


def test_first_tick_after_joining_does_not_wait():
    gate = LockstepGate(("classifier",), wants=lambda key: True)
    gate.begin(10, {"falconry/uav1/points": 400})
    assert gate.missing(UP) == []
