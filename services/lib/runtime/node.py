"""The service base every Falconry process is built on.

A Node opens one Zenoh session and always closes it, declares typed publishers and
subscribers, a liveliness token (falconry/<scope>/alive/<service>) and a health queryable,
and runs a single-threaded loop: Zenoh callbacks only push raw payloads onto a queue
(they never block or call Zenoh), and the loop decodes and dispatches them. A payload
that fails to decode is counted and logged with its key expression, never raised.

Time: the loop follows the simulator's clock ticks (or a local wall-clock ticker
onboard) and calls `on_tick(now_ns)` after the inputs of that tick. In lockstep mode
inputs are released by a LockstepGate and every tick is acknowledged, which makes a
seeded run identical whatever the machine's load.

Subclasses set `service`, optionally `upstream` and `params_type`, and override
`setup`, `on_tick` and `on_shutdown`.
"""
from __future__ import annotations

import gc
import logging
import math
import os
import queue
import signal
import threading
import time
import traceback
from typing import Any, Callable, ClassVar

import msgspec
import zenoh

from schemas import keys
from schemas.messages import Decision, FaultCommand, Header, ServiceHealth, SimClock, StepAck
from services.lib.runtime.clock import MissionClock, WallClock
from services.lib.runtime.delivery import Freshness, SimulatedNetwork
from services.lib.runtime.health import process_usage
from services.lib.runtime.lockstep import INPUT_WAIT_S, MESSAGE_WAIT_S, FaultWindows, LockstepGate
from services.lib.runtime.typed import Counters, M, Subscription, TypedPublisher
from services.lib.runtime.warmup import import_modules
from services.lib.runtime.zenoh_config import OpenCancelled, ZenohSettings, init_logging, open_session, undeclare_all

POLL_S = 0.1  # how often the loop looks at stop requests when idle
REDECLARE_EVERY_S = 10.0  # a subscription a lockstep wait gave up on is declared again at most this often
KEEP = 1  # real time: per key, only the newest message waits unread (keep-last); older ones are shed
MAX_CLOCK_JUMP_S = 1e9  # s (~30 years): a clock_jump beyond is not a clock (NaN and infinity included)
CLOCK_STEP_WARN_S = 0.5  # a system clock moved this far against the monotonic one is reported


class NoParams(msgspec.Struct, forbid_unknown_fields=True):
    pass


class _MissionTimeLog(logging.LoggerAdapter):
    """Every log line of a node carries the mission time it was written at (the wall time is the
    formatter's), so a run's log reads against its summary and ground truth."""

    def process(self, msg, kwargs):
        return f"[t={self.extra.clock.now_ns() / 1e9:.2f}] {msg}", kwargs


class Node:
    service: ClassVar[str] = ""
    # Same-scope services whose output of tick k this service consumes in tick k (lockstep).
    upstream: ClassVar[tuple[str, ...]] = ()
    params_type: ClassVar[type[msgspec.Struct]] = NoParams

    def __init__(
        self,
        uav: str | None,
        zenoh_settings: ZenohSettings,
        params: msgspec.Struct | None = None,
        clock: str = "sim",
        tick_hz: float = 20.0,
        exit_with_parent: bool = False,
        options: Any = None,
        simulated_faults: bool | None = None,
    ) -> None:
        if not self.service:
            raise TypeError("a Node subclass must set `service`")
        self.uav = uav
        self.scope = keys.scope_of(self.service, uav)
        self.sender = f"{self.scope}/{self.service}"
        self.params = params if params is not None else self.params_type()
        self.options = options  # the parsed command line, for service-specific options
        self.log = _MissionTimeLog(logging.getLogger(self.sender), self)
        self.counters = Counters()
        self.clock: MissionClock | WallClock = MissionClock() if clock == "sim" else WallClock()
        self._clock_kind = clock
        self._tick_period_ns = int(1e9 / tick_hz)
        self._zenoh_settings = zenoh_settings
        self._exit_with_parent = exit_with_parent
        self._parent = os.getppid()
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._stop = threading.Event()
        self._subs: list[Subscription] = []
        self._zenoh_handles: list[Any] = []
        self._subscribers: dict[int, Any] = {}  # Subscription.index -> its Zenoh subscriber
        self._declared_again: dict[int, float] = {}  # Subscription.index -> monotonic s of its last re-declaration
        self._publishers: list[TypedPublisher] = []
        self._liveliness_handlers: list[tuple[str, Callable[[str, bool], None], bool]] = []
        self._import_when_up: tuple[str, ...] = ()  # see import_when_up
        self._tick_alive: set[str] = set()  # lockstep: the alive set of the last tick
        self._pending_live: list[tuple[Callable, str, bool]] = []  # token events before the first tick
        self._alive_upstream: set[str] = set()
        self._lockstep: bool | None = None  # unknown until the first clock tick
        self._pending: list[tuple[Subscription, str, Any]] = []  # data before the first tick
        self._wants_cache: dict[str, bool] = {}
        self._order_cache: dict[str, tuple[int, str]] = {}
        self._gate: LockstepGate = LockstepGate(self.upstream, self._wants, self._order)
        self._last_step = -1
        self._started_wall = time.monotonic()
        self.state = "starting"
        self.session: zenoh.Session | None = None
        self._declared = False
        self._deferred_clock: SimClock | None = None
        self._last_ack: StepAck | None = None
        self._simulator_lost = False
        self._mission_over = False  # the last tick said the mission is finished
        self._warned_no_clock = False
        self._fault_windows = FaultWindows()
        # The simulator's fault commands are obeyed in a simulation only (None: on the simulator's
        # clock, off on the wall clock): onboard no message on the network can slow, reorder or
        # part a service, and the delivery path has no fault code in it.
        self._simulated_faults = clock == "sim" if simulated_faults is None else simulated_faults
        self._network: SimulatedNetwork | None = SimulatedNetwork(self.scope, self.service) \
            if self._simulated_faults else None
        self._freshness = Freshness()
        self._queued: dict[str, int] = {}  # key -> samples in the inbox (Zenoh threads add, the loop takes)
        self._queued_lock = threading.Lock()
        self._reported_clock_step = 0
        self._decode_log_budget = 20

    # ------------------------------------------------------------------ API
    def setup(self) -> None:
        """Declare publishers and subscriptions; build the core."""

    def on_tick(self, now_ns: int) -> None:
        """Called once per clock tick, after that tick's inputs were handled."""

    def on_shutdown(self) -> None:
        """Called before the session closes (publish a last message, flush files)."""

    def publisher(self, key: str, msg_type: type[M]) -> TypedPublisher[M]:
        pub = TypedPublisher(self, key, msg_type)
        self._publishers.append(pub)
        return pub

    def topic(self, name: str, uav: str | None = None) -> str:
        """Key expression of a per-UAV topic of this node's UAV (or another one)."""
        return keys.uav(uav or self.uav, name)

    def subscribe(self, key_expr: str, msg_type: type[M], handler: Callable[[M, str], None],
                  keep: int | None = KEEP) -> None:
        """handler(msg, key) for every message on key_expr. In real time, when a slow loop lets
        messages of one key queue up, all but the newest `keep` are shed unread and counted
        (None: never shed, for streams of increments or events: map deltas, fault commands)."""
        self._add_subscription(key_expr, msg_type, handler, internal=False, keep=keep)

    def on_liveliness(self, key_expr: str, handler: Callable[[str, bool], None], internal: bool = False) -> None:
        """handler(key, alive) for every token matching key_expr, current ones included.
        In lockstep the simulator's view, carried by each tick, replaces raw token events
        (internal runtime handlers excepted), so that they too land on the same tick every run."""
        self._liveliness_handlers.append((key_expr, handler, internal))
        if self._declared:
            self._declare_liveliness_subscriber(key_expr, handler, internal)

    def import_when_up(self, *modules: str) -> None:
        """Import these slow libraries right after the liveliness token, not before it
        (services/lib/runtime/warmup.py); call from setup."""
        self._import_when_up += modules

    def subscribe_runtime(self, key_expr: str, msg_type: type[M], handler: Callable[[M, str], None]) -> None:
        """A subscription to run plumbing (acknowledgements and the like): handled as it arrives,
        never held for a tick, shed or filtered."""
        self._add_subscription(key_expr, msg_type, handler, internal=True)

    def drive_clock(self, lockstep: bool) -> LockstepGate:
        """Make this node the run's clock master (the simulator) instead of a follower of the clock:
        it subscribes to no clock, and in lockstep its inputs wait in the returned gate until the
        master releases them for the tick they belong to (`begin`, `missing`, `release`)."""
        if self._declared:
            raise RuntimeError("drive_clock must be called before the node declares its subscriptions")
        self._clock_kind = "master"
        self._lockstep = lockstep
        self._gate = LockstepGate((), self._wants, self._order, joining=False)
        return self._gate

    def handle_released(self, released: list[tuple[str, tuple[Subscription, Any]]]) -> None:
        """The clock master's side of `drive_clock`: handle what its gate released for a tick."""
        for key, (sub, msg) in released:
            self._call(sub.handler, msg, key)

    @property
    def fault_windows(self) -> FaultWindows:
        """Which services the scheduled faults announced so far silence, and which radios they cut."""
        return self._fault_windows

    def stop(self) -> None:
        self._stop.set()
        self._inbox.put(("wake",))

    @property
    def lockstep(self) -> bool:
        return bool(self._lockstep)

    @property
    def real_time(self) -> bool:
        """The clock runs on its own (onboard, or a simulation without lockstep): a stage that acts
        on an input as it arrives, instead of at the next tick, spares the data up to a tick's age.
        In lockstep every input belongs to a tick, and acting on it there changes nothing. False
        until the first tick says which (the clock is at that tick's time by then)."""
        return self._lockstep is False

    # ------------------------------------------------------------ plumbing
    def _add_subscription(self, key_expr, msg_type, handler, internal: bool, keep: int | None = None) -> None:
        for other in self._subs:
            if not (internal or other.internal) and zenoh.KeyExpr(other.key_expr).intersects(zenoh.KeyExpr(key_expr)):
                # a sample of both would reach each subscription with the same key, seq and stamp, and
                # the duplicate filter (real time) or the lockstep gate would hand it to one only
                # (run plumbing is handled as it arrives, never filtered, so it may overlap)
                raise ValueError(f"subscription {key_expr!r} overlaps {other.key_expr!r} of the same node: "
                                 "subscribe once and dispatch by key in the handler")
        sub = Subscription(len(self._subs), key_expr, msgspec.msgpack.Decoder(msg_type), handler, internal, keep)
        self._subs.append(sub)
        self._wants_cache.clear()
        self._order_cache.clear()
        self._gate.rewant()
        if self._declared:
            self._declare_subscriber(sub)

    def _declare_subscriber(self, sub: Subscription) -> None:
        inbox, queued, lock = self._inbox, self._queued, self._queued_lock

        def on_sample(sample: zenoh.Sample, sub=sub) -> None:
            key = str(sample.key_expr)
            if not sub.internal:
                with lock:
                    queued[key] = queued.get(key, 0) + 1
            inbox.put(("data", sub, key, sample.payload.to_bytes()))

        handle = self.session.declare_subscriber(sub.key_expr, on_sample)
        self._zenoh_handles.append(handle)
        self._subscribers[sub.index] = handle

    def _declare_again(self, keys_missing: list[str]) -> None:
        """Declare the subscriptions a lockstep wait gave up on again, at most once per
        REDECLARE_EVERY_S each. Once in about 150 campaign runs on a loaded machine, a tracker got
        not one of its own UAV's detections for the whole run, while the acknowledgements naming
        them came from the same publisher's session over the same link: its subscription had not
        reached that publisher. The old one is undeclared first: Zenoh sends nothing for a second
        subscriber on a key its session already subscribes (the twin shares the first one's
        declaration) nor for undeclaring one of two, so declared first, the new one never left the
        process. The gap misses nothing the wait has not given up on: this service's ack of the
        tick follows the declaration on the same link, so the router knows the new subscriber
        before the next tick's messages are published."""
        now = time.monotonic()
        for sub in self._subs:
            if sub.internal or now - self._declared_again.get(sub.index, -math.inf) < REDECLARE_EVERY_S:
                continue
            expr = zenoh.KeyExpr(sub.key_expr)
            if not any(expr.intersects(zenoh.KeyExpr(key)) for key in keys_missing):
                continue
            self._declared_again[sub.index] = now
            old = self._subscribers.pop(sub.index, None)
            if old is not None:
                self._zenoh_handles.remove(old)
                undeclare_all([old])
            self._declare_subscriber(sub)
            self.log.warning("declared the subscription %s again: what a live publisher sent on it did not come",
                             sub.key_expr)

    def _declare_liveliness_subscriber(self, key_expr, handler, internal: bool) -> None:
        inbox = self._inbox

        def on_token(sample: zenoh.Sample) -> None:
            inbox.put(("live", handler, str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT, internal))

        self._zenoh_handles.append(
            self.session.liveliness().declare_subscriber(key_expr, on_token, history=True)
        )

    def _wants(self, key: str) -> bool:
        hit = self._wants_cache.get(key)
        if hit is None:
            ke = zenoh.KeyExpr(key)
            hit = any(not s.internal and zenoh.KeyExpr(s.key_expr).intersects(ke) for s in self._subs)
            self._wants_cache[key] = hit
        return hit

    def _order(self, key: str) -> tuple[int, str]:
        hit = self._order_cache.get(key)
        if hit is None:
            ke = zenoh.KeyExpr(key)
            first = min((s.index for s in self._subs if zenoh.KeyExpr(s.key_expr).intersects(ke)), default=1 << 30)
            hit = self._order_cache[key] = (first, key)
        return hit

    def _handle_signal(self, signum, frame) -> None:
        self.stop()

    @classmethod
    def preload(cls) -> None:
        """What every process of this service does before its first message whatever its
        parameters: load or compile its kernels, warmed up with the default parameters (whose
        types are any run's). The launcher's fork server calls it once for all the service's forks
        (services/tools/launcher/forkserver.py); `setup` still warms up with the run's own parameters,
        and finds the kernels ready. Nothing by default."""

    # ---------------------------------------------------------------- run
    def run(self) -> int:
        """Serve until stopped (SIGTERM/SIGINT, stop(), or the parent process dying).

        A Zenoh that does not answer yet is waited for (see `open_session`); a stop request
        meanwhile ends the wait within POLL_S and the run with 0."""
        init_logging()
        if threading.current_thread() is threading.main_thread():
            signal.signal(signal.SIGTERM, self._handle_signal)
            signal.signal(signal.SIGINT, self._handle_signal)
        try:
            self.session = open_session(self._zenoh_settings, wait=self._wait_unless_stopped, logger=self.log)
        except OpenCancelled:
            self.log.info("stopped before zenoh answered")
            return 0
        token = None
        try:
            self.declare()
            token = self.session.liveliness().declare_token(keys.alive(self.scope, self.service))
            import_modules(self._import_when_up)
            self.state = "running"
            # Everything set up so far (modules, numba's dispatchers, scipy) lives as long as the
            # process: out of the collector's sight, the final collection at exit no longer walks
            # it (that took 0.6-2 s per process when a whole fleet stopped at once on 2 cores,
            # past the launcher's 2 s grace), nor does any full collection while the service runs.
            gc.freeze()
            self.log.info("up (pid %d)", os.getpid())
            self.serve()
            self.state = "stopping"
            self.on_shutdown()
        finally:
            if token is not None:
                token.undeclare()
            undeclare_all(self._zenoh_handles)
            self.session.close()
            self.session = None
        self.log.info("stopped")
        return 0

    def declare(self) -> None:
        """Everything this node declares on `self.session` before its liveliness token: the
        runtime's inputs (clock, upstream acks, faults, liveliness), the service's own (setup),
        the ack publisher and the health queryable."""
        if self._clock_kind == "sim":
            self._add_subscription(keys.CLOCK, SimClock, self._on_clock, internal=True)
        for service in self.upstream:
            self._add_subscription(keys.ack(self.scope, service), StepAck, self._on_upstream_ack, internal=True)
        if self._simulated_faults:  # a scheduled fault can silence an upstream service or part us from a partner
            self._add_subscription(keys.FAULTS, FaultCommand, self._on_fault, internal=True)
        self.on_liveliness(f"{keys.ROOT}/{self.scope}/alive/*", self._on_scope_liveliness, internal=True)
        if self._clock_kind == "sim":
            self.on_liveliness(keys.alive(keys.SIM, "simulator"), self._on_simulator_liveliness, internal=True)
        self.setup()
        for sub in self._subs:
            self._declare_subscriber(sub)
        for key_expr, handler, internal in self._liveliness_handlers:
            self._declare_liveliness_subscriber(key_expr, handler, internal)
        self._declared = True
        self._ack_pub = self.publisher(keys.ack(self.scope, self.service), StepAck)
        inbox = self._inbox
        self._zenoh_handles.append(
            self.session.declare_queryable(keys.health(self.scope, self.service), lambda q: inbox.put(("query", q)))
        )

    def serve(self) -> None:
        """The main loop; the simulator replaces it with its own clock-driving loop."""
        self._loop()

    def pump(self, timeout: float) -> bool:
        """Handle at most one queued input; False when none came within `timeout`."""
        item = self._next_item(timeout)
        if item is None:
            self._check_parent()
            return False
        self._dispatch(item)
        return True

    def _next_item(self, timeout: float) -> tuple | None:
        """The next inbox item, or None after `timeout`. A sample a reorder fault holds back is let
        go as soon as nothing else waits."""
        if self._network is not None and self._network.holding():
            try:
                return self._inbox.get_nowait()
            except queue.Empty:
                for sample in self._network.flush():
                    self._deliver(*sample)
                return None
        try:
            return self._inbox.get(timeout=max(0.0, timeout))
        except queue.Empty:
            return None

    @property
    def stopping(self) -> bool:
        return self._stop.is_set()

    def _loop(self) -> None:
        next_wall_tick = time.monotonic()
        while not self._stop.is_set():
            timeout = POLL_S
            if self._clock_kind == "wall":
                timeout = max(0.0, min(POLL_S, next_wall_tick - time.monotonic()))
            item = self._next_item(timeout)
            if item is not None:
                self._dispatch(item)
            if self._clock_kind == "wall" and time.monotonic() >= next_wall_tick:
                next_wall_tick += self._tick_period_ns / 1e9
                self._lockstep = False
                self._flush_pending()
                self._watch_system_clock()
                self._tick(self.clock.now_ns())
            self._check_parent()

    def _wait_unless_stopped(self, seconds: float) -> bool:
        """Sleep up to `seconds`; True as soon as a stop is requested (or the parent is gone)."""
        deadline = time.monotonic() + seconds
        while not self._stop.wait(max(0.0, min(POLL_S, deadline - time.monotonic()))):
            self._check_parent()
            if time.monotonic() >= deadline:
                return self._stop.is_set()
        return True

    def _check_parent(self) -> None:
        if self._exit_with_parent and os.getppid() != self._parent:
            self.log.warning("parent process gone; stopping")
            self._stop.set()

    def _dispatch(self, item: tuple) -> None:
        kind = item[0]
        if kind == "data":
            _, sub, key, payload = item
            if sub.internal:
                msg = self._decode(sub, key, payload)
                if msg is not None:
                    self._call(sub.handler, msg, key)
                return
            with self._queued_lock:
                behind = self._queued[key] = self._queued.get(key, 1) - 1
            if self._lockstep is False and sub.keep is not None and behind >= sub.keep:
                self._count(self.counters.dropped_backlog, key)  # newer ones wait: this one is history
                return
            if self._network is None:
                self._deliver(sub, key, payload)
                return
            for sample in self._network.through(key, (sub, key, payload), self.clock.now_ns() / 1e9):
                self._deliver(*sample)
        elif kind == "live":
            _, handler, key, alive, internal = item
            if internal or self._lockstep is False:
                self._call(handler, key, alive)
            elif self._lockstep is None:
                self._pending_live.append((handler, key, alive))
        elif kind == "query":
            self._answer_health(item[1])

    def _deliver(self, sub: Subscription, key: str, payload: bytes) -> None:
        msg = self._decode(sub, key, payload)
        if msg is None:
            return
        if self._network is not None and (delay := self._network.delay(self.clock.now_ns() / 1e9)) > 0:
            time.sleep(delay)  # a `slow` fault: this computer takes longer over every message
        if self._lockstep:
            if not self._gate.hold(key, msg.header.seq, (sub, msg), msg.header.stamp):
                self._count(self.counters.dropped_stale, key)
        elif self._lockstep is None:
            self._hold_until_clock(sub, key, msg)
        else:
            self._handle(sub, key, msg)

    def _handle(self, sub: Subscription, key: str, msg: Any) -> None:
        """Real time: the newest message of a key wins; a duplicate or an overtaken one is dropped."""
        if self._freshness.fresh(key, msg.header.seq, msg.header.stamp, ordered=sub.keep is not None):
            self._call(sub.handler, msg, key)
        else:
            self._count(self.counters.dropped_stale, key)

    @staticmethod
    def _count(counter: dict[str, int], key: str) -> None:
        counter[key] = counter.get(key, 0) + 1

    def _decode(self, sub: Subscription, key: str, payload: bytes):
        try:
            msg = sub.decoder.decode(payload)
        except (msgspec.DecodeError, msgspec.ValidationError, ValueError) as exc:
            errors = self.counters.decode_errors
            errors[key] = errors.get(key, 0) + 1
            if self._decode_log_budget > 0 or errors[key] % 100 == 0:
                self._decode_log_budget -= 1
                self.log.warning("dropped undecodable payload on %s (%d bytes): %s", key, len(payload), exc)
            return None
        self.counters.received[key] = self.counters.received.get(key, 0) + 1
        return msg

    def _call(self, handler: Callable, *args) -> None:
        try:
            handler(*args)
        except Exception:
            self.counters.handler_errors += 1
            self.log.error("handler %s failed:\n%s", getattr(handler, "__name__", handler), traceback.format_exc())

    def _hold_until_clock(self, sub: Subscription, key: str, msg: Any) -> None:
        """Before the first tick the mode is unknown; keep the newest message per key only
        (a service left without a simulator must not hoard point clouds)."""
        if not self._pending and not self._warned_no_clock:
            self.log.info("waiting for the simulator's clock on %s (onboard, run with --clock wall)", keys.CLOCK)
            self._warned_no_clock = True
        self._pending = [(s, k, m) for s, k, m in self._pending if k != key] + [(sub, key, msg)]

    def _flush_pending(self) -> None:
        if not self._lockstep:
            for handler, key, alive in self._pending_live:
                self._call(handler, key, alive)
        self._pending_live = []
        pending, self._pending = self._pending, []
        for sub, key, msg in pending:
            if self._lockstep:
                self._gate.hold(key, msg.header.seq, (sub, msg), msg.header.stamp)
            else:
                self._handle(sub, key, msg)

    # ------------------------------------------------------------- clock
    def _on_clock(self, tick: SimClock, key: str) -> None:
        while tick is not None:
            self._process_tick(tick)
            tick, self._deferred_clock = self._deferred_clock, None

    def _process_tick(self, tick: SimClock) -> None:
        if self._simulator_lost:
            self._follow_restarted_simulator(tick)
        if tick.step <= self._last_step:
            if tick.step == self._last_step and tick.lockstep and self._last_ack is not None:
                self._ack_pub.put(self._last_ack)  # re-sent because our ack was lost (a router restart)
            return  # a re-sent tick we already processed
        first = self._lockstep is None
        self._lockstep = tick.lockstep
        self._mission_over = tick.finished
        self.clock.advance_to(tick.header.stamp)  # before the held messages: in real time they are handled now
        if first:
            self._flush_pending()
        if not tick.lockstep:
            self._last_step = tick.step
            self._tick(tick.header.stamp)
            return
        if self._last_step >= 0 and tick.step != self._last_step + 1:
            self._gate.rejoin()  # we missed ticks (cut off, frozen): what was sent then is gone
        self._gate.begin(tick.step, tick.bounds, self._radio_cut(tick.header.stamp / 1e9),
                         counted=self.sender in tick.alive)
        self._wait_for_gate(tick.step)
        if self._stop.is_set():
            return
        self._apply_tick_liveliness(tick.alive, self._radio_cut(tick.header.stamp / 1e9))
        for key, (sub, msg) in self._gate.release(self._answering_upstream()):
            self._call(sub.handler, msg, key)
        self._last_step = tick.step
        self._tick(tick.header.stamp)
        # every key, even those still at 0: a downstream then holds a restarted publisher's
        # first messages until an ack names them
        self._last_ack = StepAck(header=Header(stamp=tick.header.stamp), step=tick.step,
                                 published=self.published_seqs())
        self._ack_pub.put(self._last_ack)

    def published_seqs(self) -> dict[str, int]:
        """Per key this node publishes on (acknowledgements excepted), the seq of its last message."""
        return {p.key: p.seq for p in self._publishers if p is not self._ack_pub}

    def _wait_for_gate(self, step: int) -> None:
        began = time.monotonic()
        deadline = began + MESSAGE_WAIT_S
        while missing := self._gate.missing(upstream := self._answering_upstream()):
            now = time.monotonic()
            if self._gate.awaiting_upstream(upstream):  # its pace is the run's, up to the master's wait
                deadline = min(now + MESSAGE_WAIT_S, began + INPUT_WAIT_S)
            remaining = deadline - now
            if self._stop.is_set():
                return
            if self._deferred_clock is not None or remaining <= 0:
                self.counters.lockstep_timeouts += 1
                self.log.warning("tick %d: gave up waiting for %s", step, ", ".join(missing[:5]))
                self._gate.give_up(upstream)
                self._declare_again([m.split("#")[0] for m in missing if "#" in m])
                return
            item = self._next_item(min(remaining, POLL_S))
            if item is None:
                self._check_parent()
                continue
            if item[0] == "data" and item[1].key_expr == keys.CLOCK:
                newer = self._decode(item[1], item[2], item[3])
                if newer is not None and newer.step != step:
                    self._deferred_clock = newer  # the simulator moved on without us, or restarted
                continue
            self._dispatch(item)

    def _radio_cut(self, now: float) -> Callable[[str], bool]:
        """Whether a key (or a "<scope>/<service>" name) is out of reach over a cut radio link
        at mission time `now`. The simulator's tick carries everything it hears over the
        airframe links: what a partner could not have sent us over the radio must not leak in."""
        return self._fault_windows.cut_off(self.scope, now)

    def _apply_tick_liveliness(self, alive: list[str], cut: Callable[[str], bool]) -> None:
        current = {name for name in alive if not cut(name)}
        for name in sorted(current ^ self._tick_alive):
            scope, service = name.split("/", 1)
            key = keys.alive(scope, service)
            ke = zenoh.KeyExpr(key)
            for key_expr, handler, internal in self._liveliness_handlers:
                if not internal and zenoh.KeyExpr(key_expr).intersects(ke):
                    self._call(handler, key, name in current)
        self._tick_alive = current

    def _tick(self, now_ns: int) -> None:
        self._call(self.on_tick, now_ns)

    def _on_upstream_ack(self, ack: StepAck, key: str) -> None:
        service = key.rsplit("/", 1)[-1]
        self._gate.record_ack(service, ack.step, ack.published)

    def _on_fault(self, command: FaultCommand, key: str) -> None:
        self._fault_windows.add(command)  # a partner's cut radio parts us too
        if command.kind == "link_cut":  # it may part keys of the tick under way
            self._gate.recut(self._radio_cut(self.clock.now_ns() / 1e9))
        if self._network.add(command, self._wants):
            self.log.warning("fault %s%s from %.2f s%s", command.kind, f" on {command.topic}" if command.topic else "",
                             command.header.stamp / 1e9, f" for {command.duration:g} s" if command.duration else "")
        if command.kind == "clock_jump" and command.uav == self.scope and command.service in ("", self.service) \
                and abs(command.jump) < MAX_CLOCK_JUMP_S:
            if isinstance(self.clock, WallClock):
                self.clock.inject_step(command.jump)  # as an NTP step or a hand-set date would move it
            else:
                self.log.info("clock_jump: this service follows the simulator's clock, not the system's")

    def _watch_system_clock(self) -> None:
        """Mission time onboard follows the monotonic clock (WallClock): a step of the system clock
        moves no timer, and is reported once per step."""
        step = self.clock.system_step_ns()
        if abs(step - self._reported_clock_step) > CLOCK_STEP_WARN_S * 1e9:
            self.log.warning("the system clock moved %+.3f s against the monotonic clock; mission time keeps "
                             "to the monotonic one", (step - self._reported_clock_step) / 1e9)
            self._reported_clock_step = step

    def _answering_upstream(self) -> set[str]:
        """Upstream services that are alive and not silenced by a scheduled fault right now."""
        now = self.clock.now_ns() / 1e9
        if not self._fault_windows.silencing(now):
            return set(self._alive_upstream)
        return {s for s in self._alive_upstream if not self._fault_windows.silenced(self.scope, s, now)}

    def _on_scope_liveliness(self, key: str, alive: bool) -> None:
        parsed = keys.parse_alive(key)
        if parsed and parsed[1] in self.upstream:
            (self._alive_upstream.add if alive else self._alive_upstream.discard)(parsed[1])

    def _on_simulator_liveliness(self, key: str, alive: bool) -> None:
        if not alive and self._last_step >= 0:
            # Gone for good and restarted, or only out of reach (a router restart): its next tick tells.
            if self._mission_over:
                self.log.info("the simulator stopped after the mission's last tick")
            else:
                self.log.warning("simulator out of reach; its next tick tells whether it restarted")
            self._simulator_lost = True

    def _follow_restarted_simulator(self, tick: SimClock) -> None:
        """A simulator back after losing sight of it: one that restarted counts its ticks (and its
        publishers their seqs) again from where it resumed, at or before our last step; one that was
        only out of reach goes on counting."""
        self._simulator_lost = False
        if tick.step <= self._last_step:
            self.log.warning("the simulator restarted at step %d: following its clock from there", tick.step)
            self._last_step = -1
            self._gate.rejoin()
            self._gate.forget_stamps()
            self.clock = MissionClock()
            self._freshness = Freshness()

    # ------------------------------------------------------------- health
    def health(self) -> ServiceHealth:
        c = self.counters
        cpu_time, memory = process_usage()
        return ServiceHealth(
            header=Header(sender=self.sender, stamp=self.clock.now_ns()),
            uav=self.scope,
            service=self.service,
            pid=os.getpid(),
            uptime=time.monotonic() - self._started_wall,
            state=self.state,
            received=dict(c.received),
            published=dict(c.published),
            decode_errors=dict(c.decode_errors),
            handler_errors=c.handler_errors,
            lockstep_timeouts=c.lockstep_timeouts,
            subscriptions=[sub.key_expr for sub in self._subs],
            cpu_time=cpu_time,
            memory=memory,
            decisions=self.decisions(),
            dropped_stale=dict(c.dropped_stale),
            dropped_backlog=dict(c.dropped_backlog),
        )

    def decisions(self) -> list[Decision]:
        """A node with a state machine tells its whole history (health answers carry it)."""
        return []

    def _answer_health(self, query: zenoh.Query) -> None:
        try:
            # our own key: replies on the query's wildcard key would be merged into one by consolidation
            query.reply(keys.health(self.scope, self.service), msgspec.msgpack.encode(self.health()))
        except Exception as exc:
            self.log.warning("health reply failed: %s", exc)
        finally:
            query.drop()
