"""Every fault type of the scenario's schedule happens at its mission time, has its effect,
and shows in the event log and the summary (one lockstep run with all of them)."""
from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh

from schemas import keys
from schemas.arrays import to_numpy
from schemas.messages import GroundTruth, Odometry, PointCloud, SimEvent, UavStatus
from services.simulator.scenario import SCENARIO_DIR
from services.tools.launcher import netns
from tests.conftest import falconry_argv
from tests.tools.run import join_run, processes_mentioning, read_summary

FAULTS = """
[[faults]]
time = 2.0
kind = "lidar_silent"
uav = "uav1"
duration = 2.0

[[faults]]
time = 5.0
kind = "lidar_nan"
uav = "uav1"
duration = 1.0

[[faults]]
time = 7.0
kind = "lidar_garbage"
uav = "uav1"
duration = 1.0

[[faults]]
time = 3.0
kind = "odometry_jump"
uav = "uav2"
offset = [2.0, 0.0, 0.0]
duration = 4.0

[[faults]]
time = 4.0
kind = "freeze"
uav = "uav2"
service = "tracker"
duration = 3.0

[[faults]]
time = 9.0
kind = "kill"
uav = "uav2"
service = "planner"

[[faults]]
time = 10.0
kind = "link_cut"
uav = "uav2"
duration = 3.0

[[faults]]
time = 15.0
kind = "kill"
uav = "uav1"
"""


def fault_scenario(tmp_path: Path) -> Path:
    text = (SCENARIO_DIR / "mbzirc.toml").read_text()
    text = re.sub(r'^sensor = "[^"]*"', 'sensor = "os0-32-512"', text, count=1, flags=re.M)  # a light LiDAR keeps the test quick
    assert 'sensor = "os0-32-512"' in text
    path = tmp_path / "faults.toml"
    path.write_text(text + FAULTS)
    return path


class Observer:
    """What the test sees from its own session on the run (like a ground station would)."""

    def __init__(self, session) -> None:
        self.scans: list[tuple[float, float, float]] = []  # (t, NaN fraction, spread of finite points)
        self.odometry: dict[int, np.ndarray] = {}
        self.truth: dict[int, np.ndarray] = {}
        self.events: list[SimEvent] = []
        self.tokens: list[tuple[float, str, bool]] = []
        self.lock = threading.Lock()
        decode_cloud = msgspec.msgpack.Decoder(PointCloud)
        decode_odometry = msgspec.msgpack.Decoder(Odometry)
        decode_truth = msgspec.msgpack.Decoder(GroundTruth)
        decode_event = msgspec.msgpack.Decoder(SimEvent)

        def on_cloud(sample):
            cloud = decode_cloud.decode(sample.payload.to_bytes())
            points = to_numpy(cloud.points).reshape(-1, 3)
            finite = points[np.isfinite(points).all(axis=1)]
            spread = float(np.linalg.norm(finite - finite.mean(axis=0), axis=1).max()) if len(finite) else 0.0
            with self.lock:
                self.scans.append((cloud.header.stamp / 1e9, float(np.isnan(points).any(axis=1).mean()), spread))

        def on_odometry(sample):
            odo = decode_odometry.decode(sample.payload.to_bytes())
            self.odometry[odo.header.stamp] = np.array(odo.pose.position)

        def on_truth(sample):
            truth = decode_truth.decode(sample.payload.to_bytes())
            self.truth[truth.header.stamp] = np.array(next(u.position for u in truth.uavs if u.name == "uav2"))

        def on_token(sample):
            with self.lock:
                self.tokens.append((time.monotonic(), str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

        self.handles = [
            session.declare_subscriber(keys.uav("uav1", "points"), on_cloud),
            session.declare_subscriber(keys.uav("uav2", "odometry"), on_odometry),
            session.declare_subscriber(keys.TRUTH, on_truth),
            session.declare_subscriber(keys.EVENTS, lambda s: self.events.append(decode_event.decode(s.payload.to_bytes()))),
            session.liveliness().declare_subscriber(keys.ALL_ALIVE, on_token),
        ]

    def close(self) -> None:
        for handle in self.handles:
            handle.undeclare()

    def event_times(self, kind: str) -> dict[str, float]:
        return {e.subject + ":" + e.detail: e.header.stamp / 1e9 for e in self.events if e.kind == kind}


@pytest.mark.timeout(600)
@pytest.mark.skipif(netns.available() is not None, reason=f"link_cut needs {netns.available()}")
@pytest.mark.slow(54)
def test_every_fault_type_happens_at_its_time_with_its_effect(tmp_path, port):
    scenario, summary_path = fault_scenario(tmp_path), tmp_path / "summary.json"
    launcher = subprocess.Popen(
        # the LiDAR pipeline alone: the faults act on it, and the camera would only add CPU
        falconry_argv("sim", str(scenario), "--uavs", "2", "--lockstep", "--duration", "18", "--port", str(port),
                      "--detector", "classifier",
                      "--lease-ms", "1000", "--quiet", "--progress", "0", "--summary-json", str(summary_path)),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    session = join_run(port)
    observer = Observer(session)
    frozen_seen = False
    try:
        deadline = time.monotonic() + 300  # the run takes about 30 s of wall time
        while launcher.poll() is None and time.monotonic() < deadline:
            # the frozen tracker is in state T while the freeze lasts
            for pid in set(processes_mentioning("tracker --uav uav2 ")) & set(processes_mentioning(f":{port}")):
                try:
                    frozen_seen |= Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "T"
                except OSError:
                    pass
            time.sleep(0.05)
        output, _ = launcher.communicate(timeout=30)
    finally:
        if launcher.poll() is None:  # a failed test still lets the launcher tear down its namespaces
            launcher.terminate()
            launcher.wait(timeout=30)
        observer.close()
        session.close()
    assert launcher.returncode == 0, output[-3000:]

    injected = observer.event_times("fault_injected")
    expected = {"uav1:lidar_silent for 2 s": 2.0, "uav1:lidar_nan for 1 s": 5.0, "uav1:lidar_garbage for 1 s": 7.0,
                "uav2:odometry_jump for 4 s": 3.0, "uav2/tracker:freeze for 3 s": 4.0, "uav2/planner:kill": 9.0,
                "uav2:link_cut for 3 s": 10.0, "uav1:kill": 15.0}
    assert injected == pytest.approx(expected), injected

    scans = sorted(observer.scans)
    silent = [t for t, _, _ in scans if 2.0 <= t < 4.0]
    assert not silent, f"uav1 scanned during its LiDAR silence: {silent}"
    assert any(t < 2.0 for t, _, _ in scans) and any(4.0 <= t < 5.0 for t, _, _ in scans)
    assert all(nan == 1.0 for t, nan, _ in scans if 5.0 <= t < 6.0) and any(5.0 <= t < 6.0 for t, _, _ in scans)
    garbage = [(nan, spread) for t, nan, spread in scans if 7.0 <= t < 8.0]
    assert garbage and all(nan == 0.0 and spread > 20 for nan, spread in garbage), garbage
    assert all(nan < 1.0 for t, nan, _ in scans if 8.0 <= t < 15.0)

    def odometry_error(t: float) -> np.ndarray:
        stamp = int(round(t * 1e9))
        return observer.odometry[stamp] - observer.truth[stamp]
    assert np.allclose(odometry_error(5.0), [2, 0, 0], atol=0.3) and np.allclose(odometry_error(2.5), 0, atol=0.3)
    assert np.allclose(odometry_error(8.0), 0, atol=0.3)

    assert frozen_seen, "the tracker was never seen stopped (SIGSTOP)"
    started = observer.event_times("fault_started")
    assert any(k.startswith("uav2/tracker") for k in started) and any(k.startswith("uav2:link_cut") for k in started)
    ended = observer.event_times("fault_ended")
    assert any(k.startswith("uav2/tracker") for k in ended) and any(k.startswith("uav2:link_cut") for k in ended)
    assert any(e.kind == "service_restarted" and e.subject == "uav2/planner" for e in observer.events)

    # link_cut: the partner's tokens vanish (lease 1 s) and come back when the link is restored
    uav2_gone = [t for t, key, alive in observer.tokens if key.startswith("falconry/uav2/") and not alive]
    uav2_back = [t for t, key, alive in observer.tokens if key.startswith("falconry/uav2/") and alive]
    assert uav2_gone and uav2_back and max(uav2_back) > min(uav2_gone)
    # the whole-UAV kill: uav1 lands by failsafe and its processes stay down
    assert any(e.kind == "emergency_landing" and e.subject == "uav1" for e in observer.events)
    restarted = [e.subject for e in observer.events if e.kind == "service_restarted"]
    assert not any(s.startswith("uav1/") for s in restarted), f"uav1 came back after a whole-UAV kill: {restarted}"

    summary = read_summary(summary_path)
    assert sum("fault_injected" in f for f in summary["faults"]) == len(expected)
    assert "faults injected: 8" in output
    assert netns.leftovers(f"f{port}") == [], "network namespaces left behind"


CUT = """
[[faults]]
time = 6.0
kind = "link_cut"
uav = "uav1"
duration = 4.0
"""


class NamespaceProbe:
    """tests.tools.probe running inside one UAV's network namespace: what reaches that UAV."""

    def __init__(self, network: netns.UavNetwork, uav: str, port: int) -> None:
        argv = network.wrap(uav, [sys.executable, "-m", "tests.tools.probe", "--connect",
                                  f"tcp/{network.host_address}:{port}", "--listen", f"tcp/{network.address(uav)}:0"])
        self.process = subprocess.Popen(argv, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        self.lines: list[dict] = []
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.process.stdout:
            self.lines.append(json.loads(line))

    def stamps(self, key: str) -> list[float]:
        return sorted(line["stamp"] for line in self.lines if line["key"] == key)

    def stop(self) -> None:
        self.process.stdin.close()
        try:
            self.process.wait(timeout=20)
        except subprocess.TimeoutExpired:  # the probe bounds its own exit; this is the backstop
            self.process.kill()
            self.process.wait(timeout=5)
        self.reader.join(timeout=5)


def wait_for_namespaces(network: netns.UavNetwork, timeout: float = 30.0) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        names = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
        links = subprocess.run(["ip", "-o", "addr", "show", "dev", network.bridge], capture_output=True, text=True).stdout
        if all(network.namespace(u) in names for u in network.uavs) and network.host_address in links:
            time.sleep(0.5)  # the last veth's addresses
            return
        time.sleep(0.05)
    raise AssertionError("the run's network namespaces never appeared")


@pytest.mark.timeout(300)
@pytest.mark.skipif(netns.available() is not None, reason=f"link_cut needs {netns.available()}")
@pytest.mark.slow(37)
def test_a_cut_link_parts_the_uav_from_partners_and_ground_but_not_from_its_vehicle(tmp_path, port):
    """During uav1's cut (t = 6..10 s) no status of uav1 reaches uav2's namespace or the ground and
    none of uav2 reaches uav1's, while uav1's own job manager keeps publishing on the simulator's
    clock (its airframe link) and the lockstep run goes on to its end. The run lasts 6 s past the
    cut: Zenoh's reconnection attempts back off to one per 4 s during it (a 14 s run, 4 s past it,
    once ended before uav1 was heard again)."""
    scenario = fault_scenario(tmp_path)
    scenario.write_text(scenario.read_text().split("[[faults]]")[0] + CUT)
    network = netns.UavNetwork(port, ["uav1", "uav2"])  # the plan the launcher derives from the port
    launcher = subprocess.Popen(
        falconry_argv("sim", str(scenario), "--uavs", "2", "--lockstep", "--duration", "16", "--port", str(port),
                      "--detector", "classifier",  # the link cut is the subject: no camera needed
                      "--lease-ms", "1000", "--quiet", "--progress", "0", "--rtf", "1"),
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    probes: dict[str, NamespaceProbe] = {}
    session = None
    try:
        wait_for_namespaces(network)
        probes = {uav: NamespaceProbe(network, uav, port) for uav in network.uavs}
        session = join_run(port, gossip_connect=False)  # the ground hears the UAVs over the hub only
        ground: list[float] = []
        decode = msgspec.msgpack.Decoder(UavStatus)
        ground_sub = session.declare_subscriber(
            keys.uav("uav1", "status"), lambda s: ground.append(decode.decode(s.payload.to_bytes()).header.stamp / 1e9))
        output, _ = launcher.communicate(timeout=240)
        ground_sub.undeclare()
    finally:
        if launcher.poll() is None:
            launcher.terminate()
            launcher.wait(timeout=30)
        if session is not None:  # before the probes end: closing towards a gone peer waits out a timeout
            session.close()
        for probe in probes.values():
            probe.stop()
    assert launcher.returncode == 0, output[-3000:]
    assert "mission time 16.0/16 s" in output, output[-2000:]

    def during_cut(stamps: list[float]) -> list[float]:
        # half a second for the last messages in flight; the link is back at t = 10.0 (the launcher
        # restores it on that tick, as the services publish theirs), so that tick's status may cross
        return [t for t in stamps if 6.5 <= t < 10.0]

    uav1, uav2 = probes["uav1"], probes["uav2"]
    own = uav1.stamps(keys.uav("uav1", "status"))
    ticks = uav1.stamps(keys.CLOCK)
    print(f"uav1's namespace: {len(during_cut(ticks))} clock ticks and {len(during_cut(own))} own statuses during "
          f"the cut, {len(during_cut(uav1.stamps(keys.uav('uav2', 'status'))))} of uav2; uav2's namespace: "
          f"{len(during_cut(uav2.stamps(keys.uav('uav1', 'status'))))} statuses of uav1; ground: "
          f"{len(during_cut(ground))} of uav1")
    # uav1 keeps its vehicle, sensors and clock: ticks and its own job manager's statuses go on
    assert len(during_cut(ticks)) >= 30 and len(during_cut(own)) >= 10, (ticks, own)
    assert max(np.diff([t for t in own if 6.0 <= t <= 10.0])) < 0.5
    # nothing crosses the cut either way, nor reaches the ground
    assert during_cut(uav1.stamps(keys.uav("uav2", "status"))) == []
    assert during_cut(uav2.stamps(keys.uav("uav1", "status"))) == []
    assert during_cut(ground) == []
    # and the link works before and after it
    assert any(t < 6.0 for t in uav2.stamps(keys.uav("uav1", "status")))
    assert any(t > 10.5 for t in uav2.stamps(keys.uav("uav1", "status"))), "uav1 never came back to uav2"
    assert netns.leftovers(f"f{port}") == [], "network namespaces left behind"
