"""The fault campaign's pure part: seeded random fault schedules, and the table of what each run
did with its faults (`falconry campaign`, `campaign_cmd.py`, runs them). A run fails when it did
not finish, broke the safety distance, had a collision, engaged no target, left the arena or had
a handler error. Runs take the campaign's scenarios in turn (and its team sizes in turn).

A run's schedule is drawn from its own seed alone (numpy's PCG64 seeded with [campaign seed, run
index]), so a campaign is the same list of runs on every machine, and each run is a lockstep
`falconry sim` with that seed: the table repeats too (wall times are left out of it).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Each kind of single fault a campaign draws from; the job managers must stay apart under any one.
KINDS = ("link_cut", "kill_hold", "kill_land", "kill_service", "freeze_service", "lidar_silent", "lidar_nan",
         "odometry_jump", "duplicate", "reorder", "slow_service", "lidar_garbage")
SERVICES = ("sensor_driver", "mapper", "tracker", "job_manager", "planner")  # present whatever the detector
TOPICS = ("odometry", "detections", "tracks", "command", "status")  # what duplicate and reorder disturb
EARLIEST = 10.0  # s: faults hit flying UAVs (take-off is over by then)
LATEST_BEFORE_END = 25.0  # s before the end: the team still has time to react before the mission timer


@dataclass(frozen=True)
class Fault:
    time: float
    kind: str  # a scenario fault kind
    uav: str
    duration: float = 0.0
    service: str = ""
    failsafe: str = "land"
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    topic: str = ""
    delay: float = 0.0

    def toml(self) -> str:
        lines = ["[[faults]]", f"time = {self.time:.2f}", f'kind = "{self.kind}"', f'uav = "{self.uav}"']
        if self.duration:
            lines.append(f"duration = {self.duration:.2f}")
        if self.service:
            lines.append(f'service = "{self.service}"')
        if self.failsafe != "land":
            lines.append(f'failsafe = "{self.failsafe}"')
        if any(self.offset):
            lines.append("offset = [" + ", ".join(f"{v:.2f}" for v in self.offset) + "]")
        if self.topic:
            lines.append(f'topic = "{self.topic}"')
        if self.delay:
            lines.append(f"delay = {self.delay:.3f}")
        return "\n".join(lines) + "\n"

    def label(self) -> str:
        what = self.kind + (f"({self.failsafe})" if self.kind == "kill" and not self.service else "")
        subject = "/".join(filter(None, (self.uav, self.service, self.topic)))
        return f"{what} {subject} t={self.time:.0f}" + (f"+{self.duration:.0f}s" if self.duration else "")


@dataclass(frozen=True)
class RunPlan:
    index: int
    seed: int
    uavs: int
    faults: list[Fault] = field(default_factory=list)
    scenario: str = "mbzirc"


def draw_runs(count: int, seed: int, duration: float, teams: tuple[int, ...] = (2, 3), faults_per_run: int = 1,
              kinds: tuple[str, ...] = KINDS, scenarios: tuple[str, ...] = ("mbzirc",)) -> list[RunPlan]:
    """`count` runs, team sizes and scenarios each taken in turn, each run with `faults_per_run`
    faults drawn from `kinds` (the draws do not depend on the scenarios)."""
    if count < 1 or faults_per_run < 1:
        raise ValueError("a campaign needs at least one run and one fault per run")
    if duration < EARLIEST + LATEST_BEFORE_END + 1.0:
        raise ValueError(f"a campaign run needs at least {EARLIEST + LATEST_BEFORE_END + 1.0:g} s of mission "
                         f"(faults fall between {EARLIEST:g} s and {LATEST_BEFORE_END:g} s before the end)")
    runs = []
    for index in range(count):
        rng = np.random.default_rng([seed, index])
        uavs = teams[index % len(teams)]
        faults = sorted((_draw(rng, uavs, duration, kinds) for _ in range(faults_per_run)), key=lambda f: f.time)
        runs.append(RunPlan(index + 1, int(rng.integers(1, 10_000)), uavs, faults, scenarios[index % len(scenarios)]))
    return runs


def _draw(rng: np.random.Generator, uavs: int, duration: float, kinds: tuple[str, ...]) -> Fault:
    kind = kinds[int(rng.integers(len(kinds)))]
    uav = f"uav{int(rng.integers(uavs)) + 1}"
    time = round(float(rng.uniform(EARLIEST, duration - LATEST_BEFORE_END)), 2)
    if kind == "link_cut":
        lasting = rng.random() < 0.5
        return Fault(time, "link_cut", uav, 0.0 if lasting else round(float(rng.uniform(3.0, 20.0)), 2))
    if kind in ("kill_hold", "kill_land"):
        return Fault(time, "kill", uav, failsafe=kind.removeprefix("kill_"))
    if kind == "kill_service":
        return Fault(time, "kill", uav, service=SERVICES[int(rng.integers(len(SERVICES)))])
    if kind == "freeze_service":
        return Fault(time, "freeze", uav, round(float(rng.uniform(2.0, 8.0)), 2),
                     service=SERVICES[int(rng.integers(len(SERVICES)))])
    if kind == "odometry_jump":
        offset = tuple(round(float(v), 2) for v in rng.uniform(-3.0, 3.0, 3))
        return Fault(time, "odometry_jump", uav, round(float(rng.uniform(2.0, 6.0)), 2), offset=offset)
    if kind in ("duplicate", "reorder"):
        return Fault(time, kind, uav, round(float(rng.uniform(2.0, 10.0)), 2), topic=TOPICS[int(rng.integers(len(TOPICS)))])
    if kind == "slow_service":
        return Fault(time, "slow", uav, round(float(rng.uniform(2.0, 8.0)), 2),
                     service=SERVICES[int(rng.integers(len(SERVICES)))], delay=round(float(rng.uniform(0.01, 0.05)), 3))
    return Fault(time, kind, uav, round(float(rng.uniform(0.5, 3.0)), 2))  # lidar_silent, lidar_nan, lidar_garbage


@dataclass
class RunResult:
    """What one run did, from its --summary-json."""

    plan: RunPlan
    outcome: str
    min_separation: float | None
    violations: int
    destroyed: int
    targets: int
    emergency_landings: int
    restarts: int
    handler_errors: int
    decode_errors: int
    lost: int
    collisions: int
    clearance: float | None  # m: the smallest body-to-obstacle clearance of the run's UAVs (attacked poles apart)
    no_target: int = 0  # attacks and interceptions aimed at no target (farther than 2 m from every one)
    false_tracks: int = 0  # confirmed tracks, over every UAV, that never matched a target
    geofence: int = 0  # episodes of a flying UAV out of the arena or above its ceiling

    @classmethod
    def from_summary(cls, plan: RunPlan, summary: dict) -> "RunResult":
        health = summary.get("health") or {}
        separation = summary.get("min_separation")
        clearances = [c["m"] for c in (summary.get("clearance") or {}).values() if c and c.get("m") is not None]
        # a run whose team was not all up at the first tick flew another mission than its seed's
        outcome = "started short" if summary.get("started_without") else summary.get("outcome", "?")
        return cls(plan=plan, outcome=outcome,
                   min_separation=None if separation is None else separation["m"],
                   violations=len(summary.get("separation_violations", [])),
                   destroyed=len(summary.get("destroyed", [])), targets=summary.get("targets", 0),
                   emergency_landings=sum("EMERGENCY_LANDING" in [s for _, s in u.get("states", [])]
                                          for u in summary.get("uavs", {}).values()),
                   restarts=len(summary.get("restarts", [])), handler_errors=health.get("handler_errors", -1),
                   decode_errors=health.get("decode_errors", -1), lost=health.get("lost_own_uav", -1),
                   collisions=len(summary.get("collisions", [])), clearance=min(clearances, default=None),
                   no_target=sum(e.get("target") is None for u in summary.get("uavs", {}).values()
                                 for e in u.get("engagements", [])),
                   geofence=len(summary.get("geofence_breaches", [])),
                   false_tracks=sum((u.get("perception") or {}).get("false_tracks", 0)
                                    for u in summary.get("uavs", {}).values()))

    @property
    def ok(self) -> bool:
        return (self.outcome == "finished" and self.violations == 0 and self.collisions == 0
                and self.handler_errors == 0 and self.no_target == 0 and self.geofence == 0)


HEADER = (f"{'run':>3} {'UAVs':>4} {'seed':>5} {'scenario':<10} {'faults':<44} {'min sep m':>9} {'viol':>4} "
          f"{'coll':>4} {'clear m':>7} {'no-tgt':>6} {'fence':>5} {'f-trk':>5} {'destroyed':>9} {'e-land':>6} {'restarts':>8} "
          f"{'handler':>7} {'decode':>6} {'lost':>5}  outcome")


def row(r: RunResult) -> str:
    faults = "; ".join(f.label() for f in r.plan.faults)
    separation = "-" if r.min_separation is None else f"{r.min_separation:.1f}"
    clearance = "-" if r.clearance is None else f"{r.clearance:.2f}"
    return (f"{r.plan.index:>3} {r.plan.uavs:>4} {r.plan.seed:>5} {r.plan.scenario[:10]:<10} {faults:<44} "
            f"{separation:>9} {r.violations:>4} {r.collisions:>4} {clearance:>7} {r.no_target:>6} {r.geofence:>5} "
            f"{r.false_tracks:>5} "
            f"{f'{r.destroyed}/{r.targets}':>9} {r.emergency_landings:>6} {r.restarts:>8} {r.handler_errors:>7} "
            f"{r.decode_errors:>6} {r.lost:>5}  {r.outcome}")


def totals(results: list[RunResult], safety_distance: float) -> list[str]:
    finished = sum(r.outcome == "finished" for r in results)
    separations = [r.min_separation for r in results if r.min_separation is not None]
    clearances = [r.clearance for r in results if r.clearance is not None]
    return [
        f"runs finished: {finished}/{len(results)}; separation violations (closer than {safety_distance:g} m): "
        f"{sum(r.violations for r in results)}; closest approach over all runs: "
        + (f"{min(separations):.1f} m" if separations else "-"),
        f"collisions: {sum(r.collisions for r in results)}; smallest clearance to an obstacle over all runs: "
        + (f"{min(clearances):.2f} m" if clearances else "-") + " (attacked balloons' poles apart)",
        f"engagements at no target: {sum(r.no_target for r in results)}; geofence breaches (out of the arena or "
        f"above its ceiling): {sum(r.geofence for r in results)}; confirmed tracks of no target: "
        f"{sum(r.false_tracks for r in results)}",
        f"handler errors: {sum(r.handler_errors for r in results)}; undecodable payloads: "
        f"{sum(r.decode_errors for r in results)}; restarts: {sum(r.restarts for r in results)}; emergency landings: "
        f"{sum(r.emergency_landings for r in results)}; own-UAV messages not received by services that ran throughout: "
        f"{sum(r.lost for r in results)}",
    ]
