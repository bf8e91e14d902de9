"""`falconry sim`: a whole multi-UAV mission on this machine.

The launcher opens the run's hub session (embedded profile: it listens on a free
loopback port and every service connects to it, then they mesh peer to peer), starts
the simulator and the six services of every UAV as separate processes, restarts any
that crash, prints progress, and at the end stops everything and prints a summary.
"""
from __future__ import annotations

import argparse
import json
import queue
import signal
import time
from collections.abc import Callable, Iterable
from pathlib import Path

import msgspec

from schemas import keys
from schemas.messages import FaultCommand, Header, ServiceHealth, SimEvent
from services.lib.runtime import shm, tls
from services.lib.runtime.health import query_health
from services.lib.runtime.zenoh_config import free_port, init_logging, open_session, tls_files
from services.simulator.options import add_simulator_options
from services.simulator.scenario import Scenario, ScenarioError, load_scenario
from services.simulator.specs import FaultSpec
from services.tools.launcher import netns
from services.tools.launcher.common import CliError, add_zenoh_options
from services.tools.launcher.faults import ROUTER, FaultExecutor
from services.tools.launcher.monitor import RunMonitor
from services.tools.launcher.params import ParamsError, params_for, read_tables
from services.tools.launcher.plan import SIMULATOR, own_router_wanted, plan_run
from services.tools.launcher.supervisor import Supervisor, describe_exit
from services.tools.launcher.view_cmd import DRAIN_S, add_view_options, check_view_options
from services.tools.recorder.record import Recorder, summary_lines
from services.tools.registry import node_class
from services.tools.viz.settings import web_address

VIEWER = "sim/viewer"
LEAVING_STATES = ("LANDING", "EMERGENCY_LANDING")
# asking again for a lockstep run's last messages: 2 s of pauses, and each question's own wait
# (its 1 s timeout when a service does not answer: 10 s at most, only while messages are missing)
SETTLE_ATTEMPTS, SETTLE_PAUSE_S = 8, 0.25
SIMULATOR_GONE_S = 1.0  # s to wait, at the end, for the stopped simulator's token to vanish from the router
RECONNECT_S = 8.0  # s to wait, after restoring cut links at the end, for every service to answer again
# s between two looks at the children (a waitpid each): the monitor's messages come hundreds a second
POLL_CHILDREN_S = 0.05
WATCHED = (keys.CLOCK, keys.TRUTH, keys.EVENTS, keys.WORLD) + tuple(
    keys.uav("*", topic) for topic in ("status", "tracks", "detections", "points_truth", "camera_detections",
                                       "command", "trajectory"))


def add_parser(commands) -> None:
    p = commands.add_parser(
        "sim", help="run a simulated multi-UAV mission (simulator + every service of every UAV)",
        description="Start the simulator and every per-UAV service as separate processes on an embedded "
                    "local Zenoh, supervise them (a crashed service is restarted), show progress and print "
                    "a summary. Ctrl-C stops everything cleanly.",
    )
    add_simulator_options(p, positional_scenario=True)
    run = p.add_argument_group("run")
    run.add_argument("--isolate", action="store_true",
                     help="run each UAV's processes in its own network namespace (root; automatic when the "
                          "scenario schedules link_cut faults)")
    run.add_argument("--port", type=int, default=0,
                     help="loopback port of the run's hub (default: a free port, so runs never collide)")
    run.add_argument("--config", metavar="FILE", help="TOML service parameters, one [service] table each")
    run.add_argument("--truth-log", metavar="FILE",
                     help="write every ground-truth message (u32 length + msgpack) to FILE")
    run.add_argument("--summary-json", metavar="FILE", help="also write the summary as JSON to FILE")
    run.add_argument("--record", metavar="FILE.mcap",
                     help="record the run's messages to an MCAP file, all but the raw camera frames (the compressed "
                          "ones are kept; replay it with `falconry replay`)")
    run.add_argument("--log-file", metavar="FILE", help="write every service's log lines to FILE")
    run.add_argument("--digest-json", metavar="FILE",
                     help="write, per key expression, the count and SHA-256 of every payload published in the run "
                          "(clock ticks and acknowledgements excepted: a tick re-sent after a lost acknowledgement "
                          "repeats both): two seeded lockstep runs must match")
    run.add_argument("--quiet", action="store_true",
                     help="do not echo service logs (progress, restarts and the summary still print)")
    run.add_argument("--progress", type=float, default=10.0, metavar="S",
                     help="print a progress line every S seconds of mission time (default 10; 0 = never)")
    run.add_argument("--wall-timeout", type=float, default=0.0, metavar="S",
                     help="give up after S seconds of wall time (default: no limit)")
    add_view_options(p.add_argument_group("see the run"),
                     "watch the run live in rerun (a plain subscriber: the mission never waits for it)")
    add_zenoh_options(p, "Embedded default: the launcher listens on --port and services connect to it.",
                      tls_identity=tls.SIM)
    p.set_defaults(handler=run_sim)


def run_sim(args: argparse.Namespace) -> int:
    run = SimRun(args)  # checks everything first: a bad option is one line, nothing started
    outcome = "interrupted"
    signal.signal(signal.SIGTERM, _interrupt)  # `kill`, `timeout` and compose stop us like Ctrl-C does
    try:
        run.setup()
        outcome = run.loop()
    except KeyboardInterrupt:
        outcome = "interrupted"
    finally:
        # a second Ctrl-C must not cut the clean-up short
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        run.teardown(outcome)
    return run.report(outcome)


def _load_checked(args: argparse.Namespace) -> tuple[Scenario, dict[str, str], float]:
    """The scenario, each UAV's positioning and the job manager's safety distance, with every
    parameter table the run's services read and the numeric options checked (a CliError, one
    line, before anything starts)."""
    try:
        scenario = load_scenario(args.scenario)
        read_tables(args.config)
        positioning = {u: scenario.positioning(u, args.positioning) for u in keys.uav_names(args.uavs or scenario.uavs)}
        services = {s for how in positioning.values() for s in keys.uav_services(args.detector, how)}
        for service in ["simulator", *sorted(services)]:
            params_for(service, node_class(service).params_type, args.config)
        safety_distance = params_for("job_manager", node_class("job_manager").params_type, args.config).safety_distance
    except (ScenarioError, ParamsError) as exc:
        raise CliError(str(exc)) from None
    check_view_options(args)
    for name, value in (("--duration", args.duration), ("--rtf", args.rtf), ("--tick", args.tick)):
        if value is not None and value <= 0:
            raise CliError(f"{name} must be positive")
    return scenario, positioning, safety_distance


def _needs_network(args: argparse.Namespace, scenario: Scenario, uavs: list[str]) -> bool:
    """Whether the run puts each UAV in its own network namespace (--isolate, link_cut faults),
    with every combination of options and faults that cannot work refused; a router_restart fault
    switches the run to its own router. Checks that every TLS identity has its files."""
    needs_network = args.isolate or any(f.kind == "link_cut" for f in getattr(scenario, "faults", []))
    if any(f.kind == "router_restart" for f in scenario.faults):
        if args.connect or args.zenoh_config or needs_network:
            raise CliError("the scenario schedules router_restart faults, which need the run's own router: "
                           "leave out --connect, --zenoh-config, --isolate and link_cut faults")
        if args.lockstep:
            # a client that loses its router sees every other token go: the simulator would tick on
            # unpaced with nobody to wait for, for the whole downtime
            raise CliError("router_restart faults need a real-time run (leave out --lockstep): while the "
                           "router is down the simulator cannot tell a paused team from a gone one")
        args.zenoh_profile = "router"  # the run's own router, which the fault restarts
    if own_router_wanted(args) and needs_network:
        raise CliError("--zenoh-profile router without --connect runs the run's own router on loopback, "
                       "which UAVs in network namespaces (--isolate, link_cut faults) cannot reach")
    if args.tls:
        if needs_network:
            raise CliError("--tls with per-UAV network namespaces (--isolate, link_cut faults): the namespaces' "
                           "addresses are not in the certificates; leave out one or the other")
        # every party's certificate, before anything starts (the launcher and the simulator are sim)
        for identity in [tls.SIM, *uavs] + ([tls.GROUND] if args.viz or args.rrd else []) \
                + ([tls.ROUTER] if own_router_wanted(args) else []):
            tls_files(args.tls, identity)
    if needs_network and (why := netns.available()):
        raise CliError(f"{'--isolate' if args.isolate else 'the scenario schedules link_cut faults, which'} "
                       f"needs per-UAV network namespaces, but {why}")
    return needs_network


class SimRun:
    """One `falconry sim` run in three steps: `setup` (network, hub session, children),
    `loop` (until the mission is over), `teardown` (stop everything, leave nothing behind);
    `report` then prints and writes the summary."""

    def __init__(self, args: argparse.Namespace) -> None:
        self.args = args
        self.scenario, self.positioning, self.safety_distance = _load_checked(args)
        self.uavs = keys.uav_names(args.uavs or self.scenario.uavs)
        self.duration = args.duration if args.duration is not None else self.scenario.duration
        self.seed = args.seed if args.seed is not None else self.scenario.seed
        needs_network = _needs_network(args, self.scenario, self.uavs)
        self.outputs = Outputs(args)
        self.started_wall = time.time()
        self.segments_before = shm.segments()
        port = args.port or free_port()
        self.network = netns.UavNetwork(port, self.uavs) if needs_network else None
        self.plan = plan_run(args, self.uavs, self.seed, self.duration, port, self.network, self.positioning)
        self.monitor = RunMonitor(self.outputs.truth, digests=args.digest_json is not None,
                                  safety_distance=self.safety_distance)
        self.monitor.speed = 0.0 if args.lockstep else args.rtf  # mission seconds per wall second
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.encoder = msgspec.msgpack.Encoder()
        self.fault_decoder = msgspec.msgpack.Decoder(FaultCommand)
        self.event_seq = 0
        self.restarted: set[str] = set()  # children the supervisor restarted
        self.session = self.events_pub = self.resume = self.recorder = None
        self.subscribers: list = []
        self.supervisor = Supervisor(echo=not args.quiet, on_restart=self._on_restart, log_file=self.outputs.log)
        self.faults = FaultExecutor(self.supervisor, self.network, self.report_event)
        self.usage: list[ServiceHealth] = []
        self.killed: list[str] = []

    # ------------------------------------------------------------------ setup
    def setup(self) -> None:
        args, plan = self.args, self.plan
        if self.network:
            self.network.setup()
        init_logging()
        if plan.router:  # the hub is one of its clients: it comes first
            self.supervisor.start(ROUTER, plan.router)
        self.session = open_session(plan.hub_settings)
        self.subscribers = [
            self.session.declare_subscriber(
                k, lambda s: self.inbox.put((str(s.key_expr), s.payload.to_bytes(), time.monotonic_ns())))
            # digests need everything; one subscription keeps each payload from arriving twice
            for k in ((f"{keys.ROOT}/**",) if args.digest_json else WATCHED + (keys.FAULTS,))]
        self.events_pub = self.session.declare_publisher(keys.EVENTS)
        self.resume = self.session.declare_queryable(keys.RESUME, lambda query: self.inbox.put(("query", query, 0)))
        self.recorder = Recorder(self.session, args.record) if args.record else None
        mode = "lockstep" if args.lockstep else f"real time x{args.rtf:g}"
        self.supervisor.say(f"{self.scenario.name}: {len(self.uavs)} UAVs, seed {self.seed}, {self.duration:g} s of "
                            f"mission time, {mode}, detector {args.detector}, zenoh {plan.hub_label}"
                            + (f", UAVs in network namespaces on {self.network.prefix}.0/24" if self.network else ""))
        if args.viz == "web":
            self.supervisor.say(f"watch the run in a browser: {web_address()}")
        if plan.viewer:
            self.supervisor.start(VIEWER, plan.viewer, restart=False)  # first, so it sees the run from the start
        for name, argv in plan.children.items():
            self.supervisor.start(name, argv)

    def report_event(self, kind: str, subject: str, detail: str) -> None:
        self.event_seq += 1
        self.events_pub.put(self.encoder.encode(SimEvent(
            header=Header(sender="sim/launcher", seq=self.event_seq, stamp=int(self.monitor.mission_time * 1e9)),
            kind=kind, subject=subject, detail=detail)))

    def _on_restart(self, name: str, code: int, _when: float) -> None:
        self.restarted.add(name)
        self.report_event("service_restarted", name, describe_exit(code))

    # ------------------------------------------------------------------- loop
    def loop(self) -> str:
        """Until the mission is over; returns the outcome."""
        args, monitor, supervisor = self.args, self.monitor, self.supervisor
        next_progress = args.progress
        finished_at = None
        outcome = "finished"
        next_poll = time.monotonic()
        while not monitor.over:
            if monitor.finished and finished_at is None:
                finished_at = time.monotonic()
            if finished_at is not None and time.monotonic() - finished_at > 3.0:
                break  # the simulator's closing event went missing: the run is over all the same
            try:
                self._dispatch(*self.inbox.get(timeout=0.1))
            except queue.Empty:
                pass
            self.faults.tick(monitor.mission_time)
            if (now := time.monotonic()) >= next_poll:
                supervisor.poll()
                next_poll = now + POLL_CHILDREN_S
            if args.progress and monitor.mission_time >= next_progress:
                supervisor.say(monitor.progress(self.duration))
                next_progress += args.progress
            if supervisor.children[SIMULATOR].failed:
                outcome = "simulator failed"
                break
            if args.wall_timeout and time.time() - self.started_wall > args.wall_timeout:
                outcome = f"wall timeout ({args.wall_timeout:g} s)"
                break
        # Messages of the last tick travel on other links and threads than the closing event:
        # take everything until the truth is complete and the keys have been quiet a moment.
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            try:
                self._dispatch(*self.inbox.get(timeout=0.2))
            except queue.Empty:
                if monitor.truth_step >= monitor.step:
                    break
        return outcome

    def _dispatch(self, key: str, payload, received_ns: int) -> None:
        if key == "query":
            answer_resume(payload, self.monitor.last_truth)
        elif key == keys.FAULTS:
            try:
                self.faults.start(self.fault_decoder.decode(payload), self.monitor.mission_time)
            except (msgspec.DecodeError, msgspec.ValidationError):
                pass
        else:
            self.monitor.handle(key, payload, received_ns)

    # --------------------------------------------------------------- teardown
    def teardown(self, outcome: str) -> None:
        """Stop everything, whatever got started; safe after a setup that failed half-way."""
        restored = self.faults.end_all()  # links come back, so a cut-off UAV can still tell its story
        if self.session is not None and outcome != "interrupted":
            # where the run's CPU went and what the job managers decided, asked while every service still
            # lives (not after Ctrl-C: no waiting then); a link just restored needs a moment to reconnect
            self.usage = self._ask_health(wait=RECONNECT_S if restored else 0.0)
        # the router last but one: the others stop cleanly while they still reach each other
        # the simulator first: the clock master's end is what every service should see end the run
        self.killed = self.supervisor.stop_all(first={SIMULATOR: 2.0}, after_first=self._await_simulator_gone,
                                               last={ROUTER: 2.0, VIEWER: DRAIN_S + 10.0})
        viewer = self.supervisor.children.get(VIEWER)
        if viewer is not None and viewer.process is not None and viewer.process.returncode not in (0, None):
            viewer.failed = True  # e.g. a live viewer that went away: its own log line says what it missed
        for handle in [*self.subscribers, self.events_pub, self.resume]:
            if handle is not None:
                handle.undeclare()
        if self.recorder:
            print("\n".join(summary_lines(self.args.record, self.recorder.close(), time.time() - self.started_wall)))
        if self.session is not None:
            self.session.close()
        self.outputs.close()
        if self.network:
            self.network.teardown()
        shm.remove_orphans(shm.segments() - self.segments_before)

    def _await_simulator_gone(self) -> None:
        """Until the router no longer holds the stopped simulator's token (so the services, on the
        same router, have been told), at most SIMULATOR_GONE_S."""
        if self.session is None:
            return
        deadline = time.monotonic() + SIMULATOR_GONE_S
        while time.monotonic() < deadline:
            try:
                replies = list(self.session.liveliness().get(keys.alive(*SIMULATOR.split("/")), timeout=0.2))
            except Exception:  # a router already gone: nobody left to tell
                return
            if not any(reply.ok is not None for reply in replies):
                time.sleep(0.1)  # the services' own callbacks and main loops, on a loaded machine too
                return
            time.sleep(0.02)

    def _ask_health(self, wait: float) -> list[ServiceHealth]:
        expected = {name for name, child in self.supervisor.children.items()
                    if name not in (VIEWER, ROUTER) and not child.held and not child.failed}
        deadline = time.monotonic() + wait
        while True:
            usage = query_health(self.session, timeout=1.0)
            if {f"{h.uav}/{h.service}" for h in usage} >= expected or time.monotonic() >= deadline:
                break
        if not self.args.lockstep:
            return usage
        stopped = stopped_services(self.scenario.faults, self.restarted)
        return until_received(usage, lambda: query_health(self.session, timeout=1.0),
                              lambda answers: health_totals(answers, stopped)["lost_own_uav"])

    # ----------------------------------------------------------------- report
    def report(self, outcome: str) -> int:
        """Print and write the summary; the exit status of the run."""
        args, monitor = self.args, self.monitor
        summary = monitor.summary()
        summary.update(outcome=outcome, scenario=self.scenario.name, seed=self.seed, lockstep=args.lockstep,
                       detector=args.detector, wall_time=round(time.time() - self.started_wall, 2),
                       killed_at_shutdown=self.killed,
                       failed_services=[c.name for c in self.supervisor.children.values() if c.failed],
                       cpu=cpu_by_service(self.usage, time.process_time(), self.supervisor.forkserver_cpu_s),
                       health=health_totals(self.usage, stopped_services(self.scenario.faults, self.restarted)))
        for h in self.usage:  # the job managers' own logs: complete even where a cut hid their statuses
            if h.decisions and h.uav in summary["uavs"]:
                summary["uavs"][h.uav]["decisions"] = [[round(d.stamp / 1e9, 2), d.state, d.reason]
                                                       for d in h.decisions]
        print_summary(summary, len(self.uavs), self.duration)
        if args.rrd:
            print(rrd_line(args.rrd, summary["mission_time"]), flush=True)
        if args.plot:
            from services.tools.launcher.plot import plot_timeline  # matplotlib loads only when asked for

            plot_timeline(monitor, args.plot, f"Falconry run: {self.scenario.name}, {len(self.uavs)} UAVs, seed "
                                              f"{self.seed}, detector {args.detector}", self.duration)
            print(f"timeline plot: {args.plot}", flush=True)
        if args.summary_json:
            Path(args.summary_json).write_text(json.dumps(summary, indent=2) + "\n")
        if args.digest_json:
            Path(args.digest_json).write_text(json.dumps(monitor.digest_summary(), indent=2, sort_keys=True) + "\n")
        if outcome == "interrupted":
            return 130
        return 0 if outcome == "finished" and not summary["failed_services"] else 1


def rrd_line(path: str, mission_s: float) -> str:
    if not Path(path).is_file():
        return f"rerun recording: {path} was not written (see the viewer's log lines above)"
    size = Path(path).stat().st_size / 1e6
    rate = f", {size / (mission_s / 60):.1f} MB per minute of mission" if mission_s > 0 else ""
    return f"rerun recording: {path}, {size:.1f} MB{rate} (open it with `rerun {path}`)"


def answer_resume(query, last_truth: bytes | None) -> None:
    """A restarted simulator asks where the run was; before the first truth there is nothing to say."""
    try:
        if last_truth is not None:
            query.reply(keys.RESUME, last_truth)
    finally:
        query.drop()


class Outputs:
    """The run's output files, opened before anything starts so a bad path is a one-line error."""

    def __init__(self, args: argparse.Namespace) -> None:

        self.truth = self.log = None
        try:
            for path in (args.summary_json, args.digest_json, args.record):
                if path and not Path(path).resolve().parent.is_dir():
                    raise FileNotFoundError(f"no such directory: {Path(path).resolve().parent}")
            self.truth = open(args.truth_log, "wb") if args.truth_log else None
            self.log = open(args.log_file, "a", buffering=1) if args.log_file else None
        except OSError as exc:
            self.close()
            raise CliError(f"cannot write an output file: {exc}") from None

    def close(self) -> None:
        for f in (self.truth, self.log):
            if f is not None:
                f.close()



def _interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _since_detection(d: dict) -> str:
    if d.get("first_detected") is None:
        return ""
    return f" (first detected t={d['first_detected']:.1f} s, {d['t'] - d['first_detected']:.1f} s later)"


def _completion_lines(s: dict) -> list[str]:
    """When every target of a kind was done, and how close two flying UAVs came."""
    lines = []
    kinds = s.get("target_kinds", {})
    for kind in sorted(set(kinds.values())):
        wanted = {tid for tid, k in kinds.items() if k == kind}
        done = [d["t"] for d in s["destroyed"] if d["target"] in wanted]
        if len(done) == len(wanted):
            lines.append(f"all {len(wanted)} {kind}s {'destroyed' if kind == 'balloon' else 'captured'} "
                         f"at t={max(done):.1f} s")
    for name, u in s.get("uavs", {}).items():  # the decisions that leave the mission, with the job manager's reason
        for t, state, reason in u.get("decisions", []):
            if state in LEAVING_STATES and reason:
                lines.append(f"t={t:.1f} s {name}: {state} ({reason})")
    for change in s.get("team_changes", []):
        area = "no area" if change["x"] is None else f"working area x {change['x'][0]:g}..{change['x'][1]:g}"
        fallen = f" (fallen: {', '.join(change['fallen'])})" if change["fallen"] else ""
        lines.append(f"t={change['t']:.1f} s {change['uav']}: {area}{fallen}")
    sep, safety = s.get("min_separation"), s.get("safety_distance")
    if sep is not None:
        verdict = ""
        if safety is not None:
            episodes = s.get("separation_violations", [])
            verdict = (f"; safety distance {safety:g} m kept" if not episodes else
                       f"; SAFETY DISTANCE {safety:g} m BROKEN {len(episodes)} time(s), first at "
                       f"t={episodes[0]['start']:.1f} s ({episodes[0]['pair']})")
        lines.append(f"closest approach of two flying UAVs: {sep['m']:.1f} m ({sep['pair']}, t={sep['t']:.1f} s)"
                     + verdict)
    lines.append(collisions_line(s.get("collisions", [])))
    lines.append(geofence_line(s.get("geofence_breaches", [])))
    return lines


def geofence_line(breaches: list[dict]) -> str:
    """'geofence: kept', or each time a UAV left the arena or rose above its ceiling."""
    if not breaches:
        return "geofence (arena, max height): kept"
    return f"GEOFENCE BREACHED: {len(breaches)} time(s)" + "".join(
        f"\n  t={b['start']:.1f} s {b['uav']} {b['m']:.1f} m out" for b in breaches)


def collisions_line(collisions: list[dict]) -> str:
    """'collisions: none', or each crash: when, who, what it hit and how fast, where."""
    if not collisions:
        return "collisions: none"
    return f"COLLISIONS: {len(collisions)}" + "".join(f"\n  t={c['t']:.1f} s {c['uav']} hit {c['detail']}"
                                                       for c in collisions)


def clearance_line(c: dict | None) -> str:
    """'1.84 m to tree2 at t=55.9 s; in attacks 0.41 m to balloon3_pole at t=70.2 s': the body's closest
    approach to an obstacle while flying, and apart from it to the pole of a balloon it attacked."""
    if c is None:
        return "not measured"
    closest = "none measured" if c["m"] is None else f"{c['m']:.2f} m to {c['to']} at t={c['t']:.1f} s"
    return closest + _attack_pole_part(c.get("attack_pole"))


def _attack_pole_part(pole: dict | None) -> str:
    return "" if pole is None else f"; in attacks {pole['m']:.2f} m to {pole['to']} at t={pole['t']:.1f} s"


def perception_line(p: dict) -> str:
    sight = "; ".join(f"{kind}s in sight in {n} scans, missed in {p['missed'][kind]} (recall "
                      f"{100 * p['recall'][kind]:.0f} %)" for kind, n in p["in_sight"].items()) or "no target in sight"
    return (f"{p['matched']} detections matched a target (within 1 m), {p['false']} false "
            f"({p['false_per_minute']:.1f} per minute); {sight}; {p['false_tracks']} of {p['confirmed_tracks']} "
            f"confirmed tracks never matched a target ({p['false_tracks_after_10s']} of those confirmed after the "
            f"first 10 s)")


def engagement_line(engagements: list[dict]) -> str:
    """'3 attacks, 1 interception, all at a target' or which went for no target, and where."""
    if not engagements:
        return "none"
    counts = [f"{n} {word}{'s' if n != 1 else ''}" for word, action in (("attack", "attack"),
              ("interception", "intercept")) if (n := sum(e["action"] == action for e in engagements))]
    wrong = [e for e in engagements if e["target"] is None]
    if not wrong:
        return f"{', '.join(counts)}, all at a target (within 2 m)"
    where = "; ".join(f"t={e['t']:.1f} s {e['action']} at ({e['aim'][0]:.1f}, {e['aim'][1]:.1f}, "
                      f"{e['aim'][2]:.1f})" + (f", nearest target {e['miss_m']:.1f} m" if e["miss_m"] is not None
                                                 else "") for e in wrong)
    return f"{', '.join(counts)}, {len(wrong)} at no target: {where}"


def cpu_by_service(usage: list[ServiceHealth], launcher_cpu_s: float, forkserver_cpu_s: float = 0.0) -> dict[str, float]:
    """CPU seconds per process at the end of the run ("uav1/mapper", "sim/simulator", "launcher",
    "forkserver"); a restarted service counts from its restart. A service forked from the fork
    server counts from its fork: the libraries it shares were loaded once, in the fork server's
    figure."""
    cpu = {f"{h.uav}/{h.service}": round(h.cpu_time, 2) for h in usage}
    cpu["launcher"] = round(launcher_cpu_s, 2)
    if forkserver_cpu_s:
        cpu["forkserver"] = round(forkserver_cpu_s, 2)
    return cpu


def stopped_services(faults: Iterable[FaultSpec | FaultCommand], restarted: set[str]) -> set[str]:
    """"<uav>/<service>" names (or "<uav>/" for every service of a UAV) that a kill or freeze fault
    stopped or the supervisor restarted: for a while they were not there to receive."""
    stopped = set(restarted)
    for fault in faults:
        if fault.kind in ("kill", "freeze"):
            stopped.add(f"{fault.uav}/{fault.service}")
    return stopped


def until_received(usage: list[ServiceHealth], ask: Callable[[], list[ServiceHealth]],
                   lost: Callable[[list[ServiceHealth]], int], attempts: int = SETTLE_ATTEMPTS,
                   pause_s: float = SETTLE_PAUSE_S) -> list[ServiceHealth]:
    """The health answers once the messages still on their way have arrived. Health is asked as soon
    as the master's last tick is acknowledged, but what a service published in that tick for one
    that is not downstream of it (the planner's reference for the job manager) is read in the next
    tick, which never comes: if it is still on its way when the question overtakes it, it counts as
    lost. So while messages are missing, ask again, up to `attempts` times: a message still on its
    way arrives, one the network lost stays lost."""
    missing = lost(usage)
    for _ in range(attempts):
        if missing == 0:
            break
        time.sleep(pause_s)
        again = ask()
        if {(h.uav, h.service) for h in again} < {(h.uav, h.service) for h in usage}:
            continue  # an answer lost on the way is not a message received
        usage, missing = again, lost(again)
    return usage


def health_totals(usage: list[ServiceHealth], stopped: set[str] = frozenset()) -> dict[str, int]:
    """What every service counted by the end of the run: payloads it could not decode, handler
    errors, lockstep waits given up, messages of its own UAV's publishers it never received
    (per subscriber: published - received on a key of its own UAV, messages shed unread included),
    messages it shed unread behind newer ones (a slow consumer in real time), and duplicates or
    overtaken messages it dropped.

    Messages not received are split by subscriber: those of services that ran throughout
    (`lost_own_uav`: the delivery's losses) and those of `stopped` ones (`missed_while_stopped`).
    A killed or frozen service misses what is sent while it is gone, and a restarted one's counters
    start again (what it received before is missing too); how many that is follows the wall time a
    process takes to stop and come back, so it differs from run to run even in lockstep."""
    published = {key: n for h in usage for key, n in h.published.items()}
    missed = {"lost_own_uav": 0, "missed_while_stopped": 0}
    for h in usage:
        was_stopped = f"{h.uav}/{h.service}" in stopped or f"{h.uav}/" in stopped
        for key, n in h.received.items():
            if key in published and key.startswith(f"falconry/{h.uav}/"):
                missed["missed_while_stopped" if was_stopped else "lost_own_uav"] += max(0, published[key] - n)
    return {"decode_errors": sum(sum(h.decode_errors.values()) for h in usage),
            "handler_errors": sum(h.handler_errors for h in usage),
            "lockstep_timeouts": sum(h.lockstep_timeouts for h in usage),
            # the master's own: a tick that went on without a service it still waited for (a frozen
            # one it does not wait for, and whatever waits that freeze caused downstream are not)
            "ticks_gone_on_without": sum(h.lockstep_timeouts for h in usage if h.service == "simulator"),
            **missed,
            "dropped_backlog": sum(sum(h.dropped_backlog.values()) for h in usage),
            "dropped_stale": sum(sum(h.dropped_stale.values()) for h in usage),
            "services_answering": len(usage)}


def cpu_line(cpu: dict[str, float]) -> str:
    """'mapper 41.0, classifier 12.3, …': each service summed over the UAVs, the largest first."""
    totals: dict[str, float] = {}
    for process, seconds in cpu.items():
        service = process.rsplit("/", 1)[-1]
        totals[service] = totals.get(service, 0.0) + seconds
    return ", ".join(f"{name} {seconds:.1f}" for name, seconds in sorted(totals.items(), key=lambda kv: -kv[1]))


def print_summary(s: dict, uav_count: int, duration: float) -> None:
    lines = [
        "",
        f"=== Falconry run summary: {s['scenario']}, {uav_count} UAVs, seed {s['seed']}, "
        f"{'lockstep' if s['lockstep'] else 'real time'}, detector {s['detector']} ===",
        f"outcome: {s['outcome']}; mission time {s['mission_time']:.1f}/{duration:g} s in {s['wall_time']:.1f} s "
        f"wall (real-time factor {s['mission_time'] / max(s['wall_time'], 1e-9):.2f}x)",
        *([f"started without {', '.join(s['started_without'])}: not up within the simulator's start-up "
           "timeout, so this run is not the one its seed names"] if s.get("started_without") else []),
        *([f"lockstep went on {s['health']['ticks_gone_on_without']} times without a service that did not "
           "answer in time, so this run is not the one its seed names"]
          if s["lockstep"] and (s.get("health") or {}).get("ticks_gone_on_without") else []),
        f"targets destroyed or captured: {len(s['destroyed'])}/{s['targets']}"
        + "".join(f"\n  t={d['t']:.1f} s {d['target']} by {d['by']}" + _since_detection(d) for d in s["destroyed"]),
    ]
    lines += _completion_lines(s)
    for name, u in s["uavs"].items():
        took = f"took off t={u['takeoff_s']:.1f} s" if u["takeoff_s"] is not None else "never took off"
        landed = f", landed t={u['landed_s']:.1f} s" if u["landed_s"] is not None else ""
        lines.append(f"{name}: {u['final_state']}; {took}{landed}; flew {u['distance_m']:.0f} m, max height "
                     f"{u['max_height_m']:.1f} m; {u['detections']} detections, {u['confirmed_tracks']} confirmed tracks")
        lines.append(f"  perception: {perception_line(u['perception'])}")
        if u["camera"]["detections"]:
            c = u["camera"]
            lines.append(f"  camera: {c['matched']} detections matched a target (within 1 m or 10 % of their "
                         f"distance), {c['false']} false "
                         f"({c['false_per_minute']:.1f} per minute)")
        lines.append(f"  engagements: {engagement_line(u['engagements'])}")
        lines.append(f"  clearance: {clearance_line(s.get('clearance', {}).get(name))}")
    lines.append("restarts: " + (", ".join(s["restarts"]) if s["restarts"] else "none"))
    injected = [f for f in s["faults"] if "fault_injected" in f]
    lines.append(f"faults injected: {len(injected)}" + "".join(f"\n  {f}" for f in s["faults"]))
    if s["cpu"]:
        lines.append("CPU per service, s (all UAVs): " + cpu_line(s["cpu"]))
    lines += data_age_lines(s.get("data_age"))
    if s.get("health"):
        h = s["health"]
        lines.append(f"service counters ({h['services_answering']} answered): {h['decode_errors']} undecodable, "
                     f"{h['handler_errors']} handler errors, {h['lockstep_timeouts']} lockstep waits given up, "
                     f"{h['lost_own_uav']} own-UAV messages not received by services that ran throughout "
                     f"({h.get('missed_while_stopped', 0)} more by ones a fault or crash stopped), "
                     f"{h['dropped_backlog']} shed by slow "
                     f"consumers, {h['dropped_stale']} duplicates or overtaken dropped")
    if s["failed_services"]:
        lines.append("gave up on: " + ", ".join(s["failed_services"]))
    if s["killed_at_shutdown"]:
        lines.append("needed SIGKILL at shutdown: " + ", ".join(s["killed_at_shutdown"]))
    print("\n".join(lines), flush=True)


def data_age_lines(ages: dict | None) -> list[str]:
    """How old the sensor data was as it left each stage (p50 / p95 / max): in a lockstep run the
    ages count whole ticks, in mission time, and say little of the machine."""
    if not ages or not ages.get("stages"):
        return []
    clock = "real time" if ages.get("real_time") else "lockstep: in ticks of mission time"
    return [f"age of the sensor data at each stage, p50 / p95 / max ({clock}):"] + [
        f"  {stage}: {row['p50_ms']:.0f} / {row['p95_ms']:.0f} / {row['max_ms']:.0f} ms ({row['count']})"
        for stage, row in ages["stages"].items()]
