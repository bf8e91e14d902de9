"""The lockstep gate decides what a service processes at each tick, independent of arrival timing."""
from services.lib.runtime.lockstep import ACK_WAIT_S, TICK_RESEND_S, LockstepGate, TickLedger, await_acks

UP = {"classifier"}


def make_gate():
    return LockstepGate(("classifier",), wants=lambda key: key.startswith("falconry/uav1/"), joining=False)


def test_waits_for_upstream_ack_and_named_messages():
    gate = make_gate()
    gate.begin(5, {"falconry/uav1/odometry": 7})
    assert "ack of classifier" in gate.missing(UP)
    assert gate.awaiting_upstream(UP) and not gate.awaiting_upstream(set())  # still working / gone
    gate.record_ack("classifier", 5, {"falconry/uav1/detections": 3})
    assert set(gate.missing(UP)) == {"falconry/uav1/odometry#7", "falconry/uav1/detections#3"}
    assert not gate.awaiting_upstream(UP)  # only messages already sent are missing now
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
    gate.record_ack("classifier", 2, {})
    assert gate.missing(UP) == ["falconry/uav1/map#2"]  # the new incarnation's #2, not the old one
    gate.hold("falconry/uav1/map", 1, "new1")
    assert gate.missing(UP) == ["falconry/uav1/map#2"]
    gate.hold("falconry/uav1/map", 2, "new2")
    assert gate.missing(UP) == []
    assert [i for _, i in gate.release(UP)] == ["new1", "new2"]


def test_release_order_is_by_key_not_arrival():
    gate = make_gate()
    gate.begin(1, {})
    gate.record_ack("classifier", 1, {})
    gate.hold("falconry/uav1/b", 1, "b")
    gate.hold("falconry/uav1/a", 1, "a")
    assert [i for _, i in gate.release(UP)] == ["a", "b"]


def test_joining_mid_run_does_not_wait_but_the_first_step_of_a_run_does_for_those_it_counted():
    late = LockstepGate(("classifier",), wants=lambda key: True)
    late.begin(10, {"falconry/uav1/points": 400})
    assert late.missing(UP) == []
    at_start = LockstepGate(("classifier",), wants=lambda key: True)
    at_start.begin(0, {"falconry/sim/truth": 1})
    assert set(at_start.missing(UP)) == {"ack of classifier", "falconry/sim/truth#1"}
    at_start.hold("falconry/sim/truth", 1, "truth1")
    at_start.record_ack("classifier", 0, {})
    assert at_start.missing(UP) == []
    assert [i for _, i in at_start.release(UP)] == ["truth1"]
    late.release(UP)
    late.rejoin()  # missed ticks (a cut link): the next one waits for nothing again
    late.begin(30, {"falconry/uav1/points": 900})
    assert late.missing(UP) == []
    # the master began without us (its start-up wait ran out): step 0 was sent before we were there
    uncounted = LockstepGate(("classifier",), wants=lambda key: True)
    uncounted.begin(0, {"falconry/sim/truth": 1}, counted=False)
    assert uncounted.missing(UP) == [] and not uncounted.awaiting_upstream(UP)
    uncounted.release(UP)
    uncounted.begin(1, {"falconry/sim/truth": 2})
    assert set(uncounted.missing(UP)) == {"ack of classifier", "falconry/sim/truth#2"}


def test_fault_windows_silence_only_the_faulted_services_for_their_duration():
    from schemas.messages import FaultCommand, Header
    from services.lib.runtime.lockstep import FaultWindows

    windows = FaultWindows()
    windows.add(FaultCommand(header=Header(stamp=10_000_000_000), kind="freeze", uav="uav2", service="tracker",
                             duration=3.0))
    windows.add(FaultCommand(header=Header(stamp=20_000_000_000), kind="kill", uav="uav1", duration=0.0))
    windows.add(FaultCommand(header=Header(stamp=2_000_000_000), kind="link_cut", uav="uav2", duration=4.0))
    windows.add(FaultCommand(header=Header(stamp=5_000_000_000), kind="lidar_silent", uav="uav1", duration=9.0))
    windows.add(FaultCommand(header=Header(stamp=1_000_000_000), kind="kill", uav="uav2", service="mapper"))
    names = {"uav1/classifier", "uav2/tracker", "uav2/mapper"}
    assert windows.unaffected(names, 9.9) == names
    assert windows.unaffected(names, 10.0) == {"uav1/classifier", "uav2/mapper"}
    assert windows.unaffected(names, 13.0) == names  # the freeze is over
    assert windows.unaffected(names, 20.0) == {"uav2/tracker", "uav2/mapper"}  # the whole UAV killed for good
    assert windows.unaffected(names, 1e6) == {"uav2/tracker", "uav2/mapper"}
    assert windows.unaffected(names, 3.0) == names  # a cut radio: the services still tick


def test_a_cut_radio_parts_a_uav_from_its_partners_but_never_from_the_simulator():
    from schemas.messages import FaultCommand, Header
    from services.lib.runtime.lockstep import FaultWindows

    windows = FaultWindows()
    windows.add(FaultCommand(header=Header(stamp=2_000_000_000), kind="link_cut", uav="uav2", duration=4.0))
    assert not windows.parted("uav1", "uav2", 1.9) and not windows.parted("uav1", "uav3", 3.0)
    assert windows.parted("uav1", "uav2", 2.0) and windows.parted("uav2", "uav3", 5.9)
    assert not windows.parted("uav2", "sim", 3.0) and not windows.parted("uav2", "uav2", 3.0)
    assert not windows.parted("uav1", "uav2", 6.0)
    # what a service asks of the tick's keys and names: the same rule, the radios looked at once
    cut = windows.cut_off("uav1", 3.0)
    assert cut("falconry/uav2/status") and cut("uav2/tracker")
    assert not cut("falconry/uav1/points") and not cut("falconry/sim/clock") and not cut("uav3/tracker")
    assert windows.cut_off("uav3", 3.0)("falconry/uav2/tracks") and windows.cut_off("uav2", 3.0)("uav3/planner")
    assert not windows.cut_off("uav1", 6.0)("falconry/uav2/status")


def test_a_key_across_a_cut_link_is_not_waited_for_and_what_leaks_through_is_dropped():
    """The cut starts on its tick, whatever the network still delivers; after the link is back the
    first message through says where the partner is (what it sent meanwhile is gone)."""
    key = "falconry/uav2/status"
    gate = LockstepGate((), wants=lambda k: True)
    gate.begin(1, {key: 3})
    gate.hold(key, 3, "s3")
    assert gate.missing(UP) == [] and [i for _, i in gate.release(UP)] == ["s3"]
    cut = lambda k: k.startswith("falconry/uav2/")  # noqa: E731
    gate.hold(key, 4, "s4 leaked")
    gate.begin(2, {key: 4}, cut)
    gate.hold(key, 5, "s5 leaked")
    assert gate.missing(UP) == [] and gate.release(UP) == []
    gate.begin(3, {key: 9})  # back: #6..#9 went out while the link was still down
    assert gate.missing(UP) == []
    assert gate.release(UP) == []
    gate.hold(key, 11, "s11")  # the first through the restored link; #10 was lost too
    gate.begin(4, {key: 10})
    assert gate.missing(UP) == [] and gate.release(UP) == []  # s11 belongs to a later tick
    gate.begin(5, {key: 11})
    assert gate.missing(UP) == [] and [i for _, i in gate.release(UP)] == ["s11"]
    gate.begin(6, {key: 12})
    assert gate.missing(UP) == [f"{key}#12"]  # from now on it is waited for again


def test_a_joined_service_never_waits_for_what_was_sent_before_it_joined():
    gate = LockstepGate(("classifier",), wants=lambda key: True)
    gate.begin(40, {"falconry/uav1/command": 6})  # command #6 went out before we existed
    assert gate.missing(UP) == []
    gate.release(UP)
    gate.begin(41, {"falconry/uav1/command": 6})
    gate.record_ack("classifier", 41, {})
    assert gate.missing(UP) == []  # still #6: nothing to wait for
    gate.begin(42, {"falconry/uav1/command": 7})
    gate.record_ack("classifier", 42, {})
    assert gate.missing(UP) == ["falconry/uav1/command#7"]  # news: wait for it
    gate.hold("falconry/uav1/command", 7, "cmd7")
    assert [i for _, i in gate.release(UP)] == ["cmd7"]


def test_a_message_given_up_on_is_not_waited_for_again_but_released_if_it_comes():
    gate = make_gate()
    gate.begin(1, {"falconry/uav1/tracks": 8})
    gate.record_ack("classifier", 1, {})
    assert gate.missing(UP) == ["falconry/uav1/tracks#8"]
    gate.give_up(UP)  # lost on the way (its publisher's session dropped and came back)
    assert gate.release(UP) == []
    gate.begin(2, {"falconry/uav1/tracks": 8})  # the publisher has sent nothing newer since
    gate.record_ack("classifier", 2, {})
    assert gate.missing(UP) == []
    gate.hold("falconry/uav1/tracks", 8, "late")
    assert [item for _, item in gate.release(UP)] == ["late"]
    gate.begin(3, {"falconry/uav1/tracks": 9})
    gate.record_ack("classifier", 3, {})
    assert gate.missing(UP) == ["falconry/uav1/tracks#9"]  # the next one is waited for as ever


def test_a_subscription_added_during_a_tick_is_waited_for_and_a_cut_during_it_parts_its_keys():
    """What the gate works out once at `begin` follows the service: a subscription declared during
    the tick (`rewant`) and a radio cut announced during it (`recut`)."""
    wanted = {"falconry/uav1/odometry"}
    gate = LockstepGate((), wants=lambda key: key in wanted, joining=False)
    gate.begin(3, {"falconry/uav1/odometry": 4, "falconry/uav2/status": 9})
    assert gate.missing(set()) == ["falconry/uav1/odometry#4"]
    wanted.add("falconry/uav2/status")
    gate.rewant()
    assert set(gate.missing(set())) == {"falconry/uav1/odometry#4", "falconry/uav2/status#9"}
    gate.hold("falconry/uav1/odometry", 4, "odo4")
    gate.hold("falconry/uav2/status", 9, "status9")
    gate.recut(lambda key: key.startswith("falconry/uav2/"))
    assert [item for _, item in gate.release(set())] == ["odo4"]  # uav2's status is across the cut


# ------------------------------------------------------------------ the master's ledger
def test_the_ledger_keeps_each_live_services_newest_acknowledgement():
    ledger = TickLedger()
    ledger.seen("uav1/tracker", True)
    ledger.seen("uav1/planner", True)
    ledger.acknowledged("uav1/tracker", 5, {"falconry/uav1/tracks": 7})
    ledger.acknowledged("uav1/tracker", 4, {"falconry/uav1/tracks": 6})  # overtaken on the way: ignored
    assert ledger.waiting(5, ["uav1/tracker", "uav1/planner", "uav2/tracker"]) == ["uav1/planner"]  # uav2's not alive
    assert ledger.waiting(6, ledger.alive()) == ["uav1/planner", "uav1/tracker"]
    ledger.acknowledged("uav1/planner", 5, {"falconry/uav1/trajectory": 2, "falconry/uav1/tracks": 9})
    assert ledger.published() == {"falconry/uav1/tracks": 7, "falconry/uav1/trajectory": 2}  # in name order
    assert ledger.published(["uav1/planner"]) == {"falconry/uav1/tracks": 9, "falconry/uav1/trajectory": 2}
    ledger.seen("uav1/tracker", False)  # gone: its acknowledgement with it
    assert ledger.alive() == {"uav1/planner"} and ledger.published() == {"falconry/uav1/tracks": 9,
                                                                          "falconry/uav1/trajectory": 2}


class _FakeTime:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_the_master_resends_a_tick_until_answered_and_gives_up_after_its_wait():
    ledger, clock, resent = TickLedger(), _FakeTime(), []
    ledger.seen("uav1/tracker", True)

    def pump(seconds: float) -> None:
        clock.now += seconds
        if clock.now >= 101.2:  # answers after 1.2 s: the tick went out twice more meanwhile
            ledger.acknowledged("uav1/tracker", 3, {})

    answered = await_acks(ledger, 3, ledger.alive, pump, lambda: resent.append(clock.now), lambda: False, clock)
    assert answered == [] and len(resent) == 2 and resent[0] > 100.0 + TICK_RESEND_S
    silent = await_acks(ledger, 4, ledger.alive, lambda s: setattr(clock, "now", clock.now + s), lambda: None,
                        lambda: False, clock)
    assert silent == ["uav1/tracker"] and clock.now - 101.2 > ACK_WAIT_S  # waited it out, then went on
    assert await_acks(ledger, 4, ledger.alive, lambda s: None, lambda: None, lambda: True, clock) == []  # stopping
    assert await_acks(ledger, 4, lambda: set(), lambda s: None, lambda: None, lambda: False, clock) == []  # silenced
