"""Simulator node: owns the mission clock and drives the run.

Each tick it applies the trajectory references the planners sent, advances the world,
publishes odometry, IMU samples, ground truth and events, then the clock tick. In lockstep mode it
waits for every live service's acknowledgement of the tick before the next one, and
tells the services (in the tick's `bounds`) exactly which messages belong to it; in
real-time mode it paces ticks at the requested real-time factor.

Before the first tick it waits until every service of every UAV is alive (automatic
start; after startup_timeout it starts without the rest and sends a started_without event); a
service that dies is no longer waited for, and is waited for again once its liveliness token
returns.

A UAV flying without GNSS (positioning "lidar": the scenario's, or --positioning) gets its
odometry from its localizer's estimate (falconry/<uav>/localization), which the simulated flight
controller flies on (services/simulator/positioning.py).

The world model carries the surveyed obstacles (the mission's a-priori map) and every UAV's body
radius; every ground truth carries the obstacles the survey lacks, for the simulated sensors and
evaluation only. A UAV that crashes (a `collision` event, core.py) is out of the mission as a
whole-UAV kill: its kill is announced on falconry/sim/faults as a scheduled one is, so the launcher
takes its services down for good and lockstep stops waiting for them.
"""
from __future__ import annotations

import math
import time

import msgspec
import numpy as np

from schemas import keys
from schemas.arrays import from_numpy, to_numpy
from schemas.messages import (
    Appearance,
    FaultCommand,
    GroundTruth,
    Header,
    ImuBatch,
    Odometry,
    Pose,
    SimClock,
    SimEvent,
    StepAck,
    TrajectoryReference,
    VehicleTruth,
    WorldModel,
)
from services.lib.geometry import heading_quaternion, wrap_angle, yaw_of
from services.lib.runtime.clock import seconds, to_ns
from services.lib.runtime.errors import UsageError
from services.lib.runtime.counted import CountedWarnings
from services.lib.runtime.lockstep import ACK_WAIT_S, LockstepGate, TickLedger, await_acks
from services.lib.runtime.node import Node
from services.simulator.core import ImuSamples, Simulation
from services.lib.imu import ImuParams
from services.simulator.positioning import EstimateRelay
from services.simulator.checks import check_team
from services.simulator.scenario import load_scenario

KILL_WAIT_S = 5.0  # s of wall time a lockstep tick waits for the processes a kill takes down to be gone


class SimulatorParams(msgspec.Struct, forbid_unknown_fields=True):
    # s of wall time to wait for every service before starting anyway. A machine's first run
    # compiles every service's kernels before its token (each core's warm_up): cold, 3 UAVs need
    # about 53 s to come up on a 2-core machine, and a run started before then gives up waiting at
    # tick 0
    startup_timeout: float = 120.0
    startup_settle: float = 1.0  # s of wall time between the last service coming up and the first tick
    world_period: float = 1.0  # s of mission time between WorldModel re-publications
    # Every UAV's IMU, a Pixhawk-class one by default: services/lib/imu.py documents each field
    # and its source. A rate_hz that is a multiple of 100 puts samples on the physics' 10 ms sub-steps.
    imu: ImuParams = msgspec.field(default_factory=ImuParams)
    # s of mission time without a new localizer estimate after which a UAV flying without GNSS
    # reports its position lost (services/simulator/positioning.py): ten scans of a 10 Hz LiDAR
    estimate_timeout: float = 1.0

    def __post_init__(self) -> None:  # the params loader reports it as one line naming the table
        if not (math.isfinite(self.estimate_timeout) and to_ns(self.estimate_timeout) > 0):
            # inf would never call an estimate old, a value below 1 ns always would
            raise msgspec.ValidationError(f"estimate_timeout must be a positive number of seconds, "
                                          f"not {self.estimate_timeout}")


def _vec(values) -> tuple[float, float, float]:
    return (float(values[0]), float(values[1]), float(values[2]))


class SimulatorNode(Node):
    service = "simulator"
    params_type = SimulatorParams

    def __init__(self, uav, zenoh_settings, **kwargs) -> None:
        super().__init__(uav, zenoh_settings, **kwargs)
        opts = self.options
        self.scenario = load_scenario(getattr(opts, "scenario", "mbzirc"))
        self.uav_names = keys.uav_names(getattr(opts, "uavs", None) or self.scenario.uavs)
        self.seed = opts.seed if getattr(opts, "seed", None) is not None else self.scenario.seed
        duration = getattr(opts, "duration", None)
        self.duration = duration if duration is not None else self.scenario.duration
        self.run_lockstep = bool(getattr(opts, "lockstep", False))
        self.rtf = float(getattr(opts, "rtf", 1.0) or 1.0)
        self.tick_s = float(getattr(opts, "tick", 0.05) or 0.05)
        if self.duration <= 0 or self.rtf <= 0 or self.tick_s <= 0:
            raise UsageError("--duration, --rtf and --tick must be positive")
        check_team(self.scenario, self.uav_names)
        override = getattr(opts, "positioning", None)
        self.positioning = {u: self.scenario.positioning(u, override) for u in self.uav_names}
        self.relay = EstimateRelay(to_ns(self.params.estimate_timeout))
        self.sim = Simulation(self.scenario, self.uav_names, self.seed, imu=self.params.imu,
                              positioning=self.positioning)
        self.ledger = TickLedger()  # the live services and their acknowledgements (this node is the clock master)
        self._vanished: set[str] = set()  # services whose token went since a kill was asked of them
        self._pending_faults = sorted(getattr(self.scenario, "faults", []), key=lambda f: f.time)
        self._refused_references = 0
        self._tallies: dict[str, int] = {}
        self._bad_input = CountedWarnings(self.log)
        self._undo_jumps: list[tuple[int, str, np.ndarray]] = []  # (mission ns, uav, offset)
        # this node makes the clock; in lockstep trajectories wait for the tick they belong to
        self.inputs: LockstepGate = self.drive_clock(self.run_lockstep)

    # -------------------------------------------------------------- wiring
    def setup(self) -> None:
        self.clock_pub = self.publisher(keys.CLOCK, SimClock)
        self.world_pub = self.publisher(keys.WORLD, WorldModel)
        self.truth_pub = self.publisher(keys.TRUTH, GroundTruth)
        self.events_pub = self.publisher(keys.EVENTS, SimEvent)
        self.faults_pub = self.publisher(keys.FAULTS, FaultCommand)
        self.odometry_pubs = {u: self.publisher(keys.uav(u, keys.ODOMETRY), Odometry) for u in self.uav_names}
        self.imu_pubs = {u: self.publisher(keys.uav(u, keys.IMU), ImuBatch) for u in self.uav_names}
        for u in self.uav_names:
            self.subscribe(keys.uav(u, "trajectory"), TrajectoryReference, self.on_trajectory)
            if self.positioning[u] == "lidar":
                self.subscribe(keys.uav(u, keys.LOCALIZATION), Odometry, self.on_localization)
        self.subscribe_runtime(keys.ALL_ACKS, StepAck, self._on_ack)
        self.on_liveliness(keys.ALL_ALIVE, self._on_alive, internal=True)

    def _on_alive(self, key: str, alive: bool) -> None:
        parsed = keys.parse_alive(key)
        if parsed is None or parsed == (keys.SIM, self.service):
            return
        name = f"{parsed[0]}/{parsed[1]}"
        self.ledger.seen(name, alive)
        if not alive:
            self._vanished.add(name)

    def _on_ack(self, ack: StepAck, key: str) -> None:
        owner = keys.ack_owner(key)
        if owner is not None:
            self.ledger.acknowledged(owner, ack.step, ack.published)

    def on_localization(self, msg: Odometry, key: str) -> None:
        """A localizer's estimate: its error becomes the flight controller's (positioning.py)."""
        uav = keys.uav_of(key)
        covariance = None if msg.covariance is None else to_numpy(msg.covariance)
        if covariance is not None and covariance.size != 36:
            covariance = None
        error = self.relay.take_estimate(uav, msg.header.stamp, msg.pose.position, yaw_of(msg.pose.orientation),
                                         covariance, msg.health)
        if error is None:
            self._bad_input.update({"localizer estimates ignored (not finite, or no truth at their stamp)":
                                    self._tally("ignored estimates")})
            return
        self.sim.set_odometry_error(uav, error.position)

    def _tally(self, what: str) -> int:
        self._tallies[what] = self._tallies.get(what, 0) + 1
        return self._tallies[what]

    def on_trajectory(self, msg: TrajectoryReference, key: str) -> None:
        uav = keys.uav_of(key)
        p = msg.profile
        try:
            self.sim.set_reference(uav, msg.start, msg.dt, np.array(to_numpy(msg.positions)),
                                   np.array(to_numpy(msg.headings)), p.max_speed, p.max_acceleration,
                                   p.max_heading_rate, p.max_vertical_speed)
        except ValueError as exc:  # the vehicle keeps its last good reference, as a flight controller would
            self._refused_references += 1
            self._bad_input.update({"trajectory references refused (empty, dt out of range or not finite)":
                                    self._refused_references})
            if self._refused_references == 1:
                self.log.warning("the first refused trajectory reference: %s", exc)

    # --------------------------------------------------------------- loop
    def expected_services(self) -> set[str]:
        detector = getattr(self.options, "detector", None) or keys.DEFAULT_DETECTOR
        return {f"{u}/{s}" for u in self.uav_names for s in keys.uav_services(detector, self.positioning[u])}

    def serve(self) -> None:
        first_step = self.resume_from_launcher()
        absent = self.wait_for_team()
        if absent is None:
            return
        if first_step == 0:
            self.event("mission_started", "sim", f"{self.scenario.name}, {len(self.uav_names)} UAVs, "
                       f"seed {self.seed}, {'lockstep' if self.run_lockstep else f'real time x{self.rtf:g}'}")
        if absent:  # a run that began short of a service is not the run its seed names: say so in the summary
            self.event("started_without", "sim", ", ".join(sorted(absent)))
        steps = int(round(self.duration / self.tick_s))
        wall_start, mission_start = time.monotonic(), seconds(to_ns(first_step * self.tick_s))
        for step in range(first_step, steps + 1):
            if self.stopping:
                return
            crashed = []
            if step > 0:
                self.handle_released(self.inputs.release(self.ledger.alive()))
                for kind, subject, detail in self.sim.step(self.tick_s):
                    self.event(kind, subject, detail)
                    if kind == "collision":
                        crashed.append(subject)
            now = to_ns(step * self.tick_s)
            self.clock.advance_to(now)
            killed = set()
            for uav in crashed:
                killed |= self.announce_crash(uav, now)
            killed |= self.inject_faults(now)
            if self.run_lockstep and killed:
                self.await_killed(killed)
            self.publish_state(step, now)
            rtf = (seconds(now) - mission_start) / max(time.monotonic() - wall_start, 1e-9)
            tick = SimClock(header=Header(stamp=now), step=step, dt=self.tick_s, lockstep=self.run_lockstep,
                            real_time_factor=rtf, bounds=self.bounds(), finished=step == steps,
                            alive=sorted(self.ledger.alive() | {self.sender}))
            self.clock_pub.put(tick)
            if self.run_lockstep:
                self.wait_for_acks(tick)
            else:
                self.pace(wall_start + (seconds(now) - mission_start + self.tick_s) / self.rtf)
        self.event("mission_finished", "sim", f"{seconds(self.clock.now_ns()):.1f} s of mission time")
        while not self.stopping:  # stay reachable (health queries) until the launcher stops us
            self.pump(0.2)

    def resume_from_launcher(self) -> int:
        """A restarted simulator continues the run from the launcher's last ground truth
        (falconry/sim/resume); returns the first step to simulate (0 for a new run)."""
        decoder = msgspec.msgpack.Decoder(GroundTruth)
        try:
            replies = list(self.session.get(keys.RESUME, timeout=1.0))
        except Exception as exc:  # no launcher (compose, onboard): a new run
            self.log.debug("no resume answer: %s", exc)
            return 0
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                truth = decoder.decode(reply.ok.payload.to_bytes())
            except (msgspec.DecodeError, msgspec.ValidationError):
                continue
            self.sim.resume(truth.header.stamp, truth.uavs, truth.targets)
            self.clock.advance_to(truth.header.stamp)
            self.event("simulator_resumed", "sim", f"from step {truth.step} (t={seconds(truth.header.stamp):.2f} s)")
            return truth.step + 1
        return 0

    def wait_for_team(self) -> set[str] | None:
        """The services still absent when the first tick may go (empty when the whole team is up),
        or None when the run is stopping."""
        expected = self.expected_services()
        deadline = time.monotonic() + self.params.startup_timeout
        while not expected <= (alive := self.ledger.alive()):
            if self.stopping:
                return None
            if time.monotonic() > deadline:
                self.log.warning("starting without %s", ", ".join(sorted(expected - alive)))
                return expected - alive
            self.pump(0.05)
        # A token says a service is up, not that its subscriptions have reached every publisher
        # (declarations travel separately): a first message sent before then is lost, and in
        # lockstep its subscriber waits for it in vain. Let the declarations settle.
        settle = time.monotonic() + self.params.startup_settle
        while time.monotonic() < settle and not self.stopping:
            self.pump(0.05)
        return set()

    def bounds(self) -> dict[str, int]:
        merged = self.ledger.published()
        merged.update({key: seq for key, seq in self.published_seqs().items() if seq and key != keys.CLOCK})
        return merged

    def wait_for_acks(self, tick: SimClock) -> None:
        # a frozen, cut-off or killed service cannot answer: not waiting is part of the fault
        silent = await_acks(self.ledger, tick.step,
                            lambda: self.fault_windows.unaffected(self.ledger.alive(), seconds(tick.header.stamp)),
                            self.pump, lambda: self.clock_pub.put(tick), lambda: self.stopping, time.monotonic)
        if silent:
            self.counters.lockstep_timeouts += 1
            self.log.warning("tick %d: no acknowledgement from %s; going on", tick.step, ", ".join(silent))
        self.inputs.begin(tick.step + 1, self.bounds())
        deadline = time.monotonic() + ACK_WAIT_S
        while (missing := self.inputs.missing(set())) and not self.stopping:
            if time.monotonic() > deadline:
                self.counters.lockstep_timeouts += 1
                self.log.warning("tick %d: gave up waiting for %s", tick.step + 1, ", ".join(missing[:5]))
                self.inputs.give_up(set())
                break
            self.pump(0.05)

    def pace(self, wall_deadline: float) -> None:
        while not self.stopping:
            remaining = wall_deadline - time.monotonic()
            if remaining <= 0:
                break
            self.pump(min(remaining, 0.05))

    # ------------------------------------------------------------ faults
    def inject_faults(self, now: int) -> set[str]:
        """The faults due by `now` injected or announced; returns the services a kill takes down."""
        killed: set[str] = set()
        while self._undo_jumps and self._undo_jumps[0][0] <= now:
            _, uav, offset = self._undo_jumps.pop(0)
            self.sim.jump_odometry(uav, -offset)
            self.event("fault_ended", uav, "odometry_jump")
        while self._pending_faults and to_ns(self._pending_faults[0].time) <= now:
            spec = self._pending_faults.pop(0)
            command = spec.command()
            self.fault_windows.add(command)  # before this tick's wait, not when it comes back to us
            if spec.kind == "odometry_jump":
                offset = np.asarray(spec.offset, dtype=float)
                self.sim.jump_odometry(spec.uav, offset)
                if spec.duration > 0:
                    self._undo_jumps.append((now + to_ns(spec.duration), spec.uav, offset))
                    self._undo_jumps.sort(key=lambda u: u[0])
            elif spec.kind == "kill" and not spec.service:
                # the flight controller's failsafe when the onboard computer dies
                if spec.failsafe == "hold":
                    self.sim.hold_position(spec.uav, "onboard computer lost")
                else:
                    self.sim.emergency_land(spec.uav, "onboard computer lost")
            target = "/".join(filter(None, (spec.uav, spec.service))) or "router"
            # the event first: the command may take the router (and with it every event) down
            self.event("fault_injected", target, spec.kind + (f" for {spec.duration:g} s" if spec.duration else ""))
            killed |= self._taken_down(command)
            self.faults_pub.put(command)
        return killed

    def announce_crash(self, uav: str, now: int) -> set[str]:
        """A crashed UAV is out of the mission as a whole-UAV kill for good (the launcher's fault
        executor takes its processes down), announced as a scheduled kill is; returns its services."""
        command = FaultCommand(header=Header(stamp=now), kind="kill", uav=uav)
        self.fault_windows.add(command)  # before this tick's wait, not when it comes back to us
        killed = self._taken_down(command)
        self.faults_pub.put(command)
        return killed

    def _taken_down(self, command: FaultCommand) -> set[str]:
        """The live services a kill command takes down (none for other faults)."""
        if command.kind != "kill":
            return set()
        prefix = f"{command.uav}/"
        alive = self.ledger.alive()
        names = {prefix + command.service} if command.service else {n for n in alive if n.startswith(prefix)}
        names &= alive
        self._vanished -= names
        return names

    def await_killed(self, names: set[str]) -> None:
        """In lockstep, the tick a kill happens at goes out once the killed processes' tokens are
        gone. The launcher kills them in wall time: going on at once, a killed service could act on
        one more tick in one run than in another of the same seed, and the two runs would differ
        (benchmarks/README.md, separation.py). At most KILL_WAIT_S of wall time: without a launcher
        nobody kills."""
        deadline = time.monotonic() + KILL_WAIT_S
        while not names <= self._vanished and not self.stopping:
            if time.monotonic() > deadline:
                self.log.warning("killed, still there after %g s: %s; going on", KILL_WAIT_S,
                                 ", ".join(sorted(names - self._vanished)))
                return
            self.pump(0.02)

    # ------------------------------------------------------------ output
    def publish_world(self) -> None:
        self.world_pub.put(world_model(self.sim, self.clock.now_ns(), self.seed, self.duration, self.positioning))

    def publish_state(self, step: int, now: int) -> None:
        if step % max(1, int(round(self.params.world_period / self.tick_s))) == 0:
            self.publish_world()
        vehicles = self.sim.vehicles()
        for v in vehicles:
            position, velocity, heading, covariance = self.sim.odometry(v.name)
            health = ""
            if self.positioning[v.name] == "lidar":
                self.relay.record_truth(v.name, now, v.position, v.heading)
                belief = self.relay.belief(v.name, now)
                if belief is not None:  # else the launch pose, known without GNSS
                    heading = float(wrap_angle(heading + belief.heading_error))
                    covariance, health = belief.covariance, belief.health
            self.odometry_pubs[v.name].put(Odometry(
                header=Header(stamp=now), pose=Pose(position=_vec(position), orientation=heading_quaternion(heading)),
                velocity=_vec(velocity), covariance=from_numpy(np.asarray(covariance, dtype=np.float64)),
                health=health))
            self.imu_pubs[v.name].put(imu_batch(self.sim.imu(v.name), now, v.name, self.sim.imu_params.rate_hz))
        self.truth_pub.put(ground_truth(self.sim, step, now, vehicles))

    def event(self, kind: str, subject: str, detail: str = "") -> None:
        self.log.info("event %s %s %s", kind, subject, detail)
        self.events_pub.put(SimEvent(header=Header(stamp=self.clock.now_ns()), kind=kind, subject=subject, detail=detail))


def world_model(sim: Simulation, stamp: int, seed: int, duration: float, positioning: dict[str, str]) -> WorldModel:
    """What every service may know of the world: the arena, the surveyed obstacles, the team."""
    sc, uavs = sim.scenario, sim.uav_names
    return WorldModel(
        header=Header(stamp=stamp), scenario=sc.name, arena=[tuple(p) for p in sc.arena],
        min_height=sc.min_height, max_height=sc.max_height, obstacles=sim.obstacles(),
        uavs=list(uavs), seed=seed, duration=duration,
        sensors={u: sc.uav_spec(u).sensor for u in uavs},
        positioning={u: "lidar" for u in uavs if positioning[u] == "lidar"},
        appearance=Appearance(sky=tuple(sc.appearance.sky), ground=tuple(sc.appearance.ground),
                              obstacle=tuple(sc.appearance.obstacle), sun_elevation=sc.appearance.sun_elevation,
                              sun_azimuth=sc.appearance.sun_azimuth, ambient=sc.appearance.ambient),
        uav_radius={u: float(sc.uav_spec(u).radius) for u in uavs})


def ground_truth(sim: Simulation, step: int, stamp: int, vehicles: list | None = None) -> GroundTruth:
    """The truth of this moment, with the obstacles the survey lacks (for sensors and evaluation)."""
    return GroundTruth(
        header=Header(stamp=stamp), step=step,
        uavs=[VehicleTruth(name=v.name, position=tuple(float(x) for x in v.position),
                           velocity=tuple(float(x) for x in v.velocity), heading=float(v.heading),
                           airborne=bool(v.airborne), alive=bool(v.alive))
              for v in (vehicles if vehicles is not None else sim.vehicles())],
        targets=[t.truth() for t in sim.targets()], obstacles=sim.unsurveyed_obstacles())


def imu_batch(samples: ImuSamples, now: int, uav: str, rate_hz: int) -> ImuBatch:
    """The message of one UAV's samples over the tick ending at `now`, in its body frame."""
    return ImuBatch(header=Header(stamp=now, frame=uav), stamps=from_numpy(samples.stamps_ns),
                    accelerometer=from_numpy(samples.accelerometer), gyroscope=from_numpy(samples.gyroscope),
                    rate_hz=rate_hz)


NODE = SimulatorNode
