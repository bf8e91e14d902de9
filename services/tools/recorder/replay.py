"""`Replayer`: publish a recording back on the original keys.

Payloads go out unchanged, with their original header.seq, except the clock ticks, which the
replayer re-issues as the run's clock master:

- paced (default): in file (receive) order at `rate` times the recorded receive times (rate 0:
  as fast as possible). Ticks go out with lockstep off and no bounds: services just follow them.
- lockstep: like the simulator (docs/architecture.md, "Time and lockstep"), so that a service
  under test sees exactly the inputs, in exactly the tick, it saw in the recorded run:
  * the replayer stands in for the publishers of the replayed data (header.sender of the
    recorded messages, e.g. sim/simulator and uav1/sensor_driver): it declares their liveliness
    tokens and replays their recorded acknowledgements (limited to replayed keys), so a service
    whose upstream is one of them waits for the same upstream bounds as in the recorded run;
  * the order comes from the recorded lockstep bookkeeping, not from file order (see
    schedule.py): per tick, what the simulator sent before it, the tick, then the pipeline
    slot by slot: a stand-in's messages and acknowledgement, or a wait for a live service's
    acknowledgement; before each tick, a wait for every live service;
  * each tick carries the recorded bounds of the replayed keys, merged with the last
    acknowledgements of the live services (their own outputs, for services downstream of them).
  A tick nobody acknowledged is re-sent after 0.5 s; waits give up after 10 s with a warning.

Acknowledgements of services that are not stood in for are never replayed.
"""
from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Iterable

import msgspec
import zenoh
from mcap.writer import MCAP0_MAGIC as MAGIC

from schemas import keys
from schemas.messages import SimClock, StepAck
from services.lib.runtime.errors import UsageError
from services.lib.runtime.lockstep import TickLedger, await_acks
from services.tools.recorder.mcap_io import ReadReport, header_of, read_recording
from services.tools.recorder.schedule import AwaitAck, AwaitAll, LockstepSchedule, Publish, Tick
from services.tools.recorder.selection import DEFAULT_REPLAY_KEYS, KeyFilter, pipeline_order

SETTLE_S = 0.3  # lets services see the stand-in tokens before the first tick
LINGER_S = 0.3  # lets the last messages leave before the session closes


class ReplayError(UsageError):
    """The replay cannot start (a service to wait for never came, a key set that cannot work)."""


@dataclass
class ReplayStats:
    published: dict[str, int] = field(default_factory=dict)
    ticks: int = 0
    ack_timeouts: int = 0
    resent_ticks: int = 0
    stood_in: list[str] = field(default_factory=list)
    read: ReadReport = field(default_factory=ReadReport)
    wall_s: float = 0.0


class Replayer:
    def __init__(self, session: zenoh.Session, path: str, key_exprs: Iterable[str] = DEFAULT_REPLAY_KEYS,
                 lockstep: bool = False, rate: float = 1.0, wait_for: Iterable[str] = (),
                 wait_timeout: float = 30.0, progress_s: float = 2.0, say: Callable[[str], None] = print,
                 stop: threading.Event | None = None) -> None:
        self.session = session
        self.path = str(path)
        self.key_exprs = list(key_exprs)
        self.replayed = KeyFilter(self.key_exprs)
        self.lockstep = lockstep
        self.rate = rate
        self.wait_for = list(wait_for)
        self.wait_timeout = wait_timeout
        self.progress_s = progress_s
        self.say = say
        self.stop = stop or threading.Event()
        with open(self.path, "rb") as file:
            if file.read(len(MAGIC)) != MAGIC:
                raise ReplayError(f"{self.path} is not an MCAP file")
        if rate < 0:
            raise ReplayError("--rate must be >= 0 (0: as fast as possible)")
        if lockstep and not self.replayed(keys.CLOCK):
            raise ReplayError(f"lockstep replay drives the services by the recorded ticks: replay {keys.CLOCK}")
        self.stats = ReplayStats()
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._changed = threading.Event()  # set by the Zenoh threads on news for the ledger
        self.ledger = TickLedger(on_change=self._changed.set)  # replay stands in for the clock master
        self._tokens: dict[str, zenoh.LivelinessToken] = {}
        self._handles: list = []
        self._published_seq: dict[str, int] = {}
        self._tick_payload: bytes | None = None
        self._tick_step: int | None = None
        self._encoder = msgspec.msgpack.Encoder()
        self._clock_decoder = msgspec.msgpack.Decoder(SimClock)
        self._ack_decoder = msgspec.msgpack.Decoder(StepAck)

    # ------------------------------------------------------------ zenoh side
    def _on_alive(self, sample: zenoh.Sample) -> None:
        parsed = keys.parse_alive(str(sample.key_expr))
        if parsed is None:
            return
        self.ledger.seen(f"{parsed[0]}/{parsed[1]}", sample.kind == zenoh.SampleKind.PUT)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        name = keys.ack_owner(str(sample.key_expr))
        if name is None or name in self._tokens:
            return  # our own stand-in acknowledgements
        try:
            ack = self._ack_decoder.decode(sample.payload.to_bytes())
        except (msgspec.DecodeError, msgspec.ValidationError):
            return
        self.ledger.acknowledged(name, ack.step, ack.published)

    def live_services(self) -> list[str]:
        """Services under test: alive, and not one this replayer stands in for."""
        return sorted(self.ledger.alive() - set(self._tokens))

    def _publish(self, key: str, payload: bytes, count: bool = True) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self._publishers[key] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK)
        pub.put(payload)
        if count:
            self.stats.published[key] = self.stats.published.get(key, 0) + 1

    # ----------------------------------------------------------------- run
    def run(self) -> ReplayStats:
        started = time.monotonic()
        try:
            self._handles.append(self.session.liveliness().declare_subscriber(keys.ALL_ALIVE, self._on_alive,
                                                                              history=True))
            if self.lockstep:
                self._handles.append(self.session.declare_subscriber(keys.ALL_ACKS, self._on_ack))
            self._stand_in(self._senders() if self.lockstep else
                           (["sim/simulator"] if self.replayed(keys.CLOCK) else []))
            self._wait_for_services()
            if self._tokens:
                time.sleep(SETTLE_S)
            if self.lockstep:
                self._run_lockstep()
            else:
                self._run_paced()
            if not self.stop.is_set():
                time.sleep(LINGER_S)
        finally:
            for handle in [*self._handles, *self._tokens.values(), *self._publishers.values()]:
                try:
                    handle.undeclare()
                except Exception:
                    pass
            self._handles, self._publishers = [], {}
            self.stats.stood_in = sorted(self._tokens)
            self._tokens = {}
        self.stats.wall_s = time.monotonic() - started
        return self.stats

    def _senders(self) -> list[str]:
        """Who published the replayed data in the recorded run (header.sender per key)."""
        senders: dict[str, str] = {}
        report = ReadReport()
        for msg in read_recording(self.path, lambda k: self.replayed(k) and keys.ack_owner(k) is None, report):
            if msg.key not in senders:
                header = header_of(msg.payload)
                senders[msg.key] = header.sender if header is not None else ""
        return sorted({s for s in senders.values() if s.count("/") == 1})

    def _stand_in(self, senders: list[str]) -> None:
        time.sleep(0.1)  # the liveliness history (tokens already there) arrives asynchronously
        for name in senders:
            if name in self.ledger.alive():
                self.say(f"warning: {name} is running and also published replayed data: not standing in for it")
                continue
            scope, service = name.split("/")
            self._tokens[name] = self.session.liveliness().declare_token(keys.alive(scope, service))
        if self._tokens:
            self.say("standing in for " + ", ".join(sorted(self._tokens)))

    def _wait_for_services(self) -> None:
        if not self.wait_for:
            return
        deadline = time.monotonic() + self.wait_timeout
        while missing := [n for n in self.wait_for if n not in self.ledger.alive()]:
            if self.stop.is_set():
                return
            if time.monotonic() > deadline:
                raise ReplayError(f"not alive after {self.wait_timeout:g} s: {', '.join(missing)}")
            self._wait_for_news(0.1)
        self.say("alive: " + ", ".join(self.wait_for))

    def _progress(self, tick: SimClock | None) -> None:
        now = time.monotonic()
        if self.progress_s and now >= self._next_progress:
            self._next_progress = now + self.progress_s
            at = f"tick {tick.step} (t={tick.header.stamp / 1e9:.1f} s), " if tick is not None else ""
            self.say(f"replay: {at}{sum(self.stats.published.values())} messages published")

    def _read(self, wanted: Callable[[str], bool]):
        report = self.stats.read
        yield from read_recording(self.path, wanted, report)
        if not report.complete:
            self.say(report.describe(self.path))

    # ------------------------------------------------------------- paced
    def _run_paced(self) -> None:
        self._next_progress = time.monotonic() + self.progress_s
        wall_start = first_log = None
        tick = None
        for msg in self._read(lambda k: self.replayed(k) and keys.ack_owner(k) is None):
            if self.stop.is_set():
                return
            if self.rate > 0:
                if wall_start is None:
                    wall_start, first_log = time.monotonic(), msg.log_time
                due = wall_start + max(0, msg.log_time - first_log) / 1e9 / self.rate
                while (left := due - time.monotonic()) > 0 and not self.stop.is_set():
                    time.sleep(min(left, 0.1))
            payload = msg.payload
            if msg.key == keys.CLOCK:
                tick = self._clock_decoder.decode(payload)
                tick.lockstep, tick.bounds = False, {}  # nobody acknowledges: services just follow
                payload = self._encoder.encode(tick)
                self.stats.ticks += 1
            self._publish(msg.key, payload)
            self._progress(tick)

    # ----------------------------------------------------------- lockstep
    def _run_lockstep(self) -> None:
        self._next_progress = time.monotonic() + self.progress_s
        schedule = LockstepSchedule(self._tokens, pipeline_order(self.say))
        wanted = lambda k: self.replayed(k) or keys.ack_owner(k) is not None  # noqa: E731
        tick = None
        for action in schedule.actions(self._read(wanted)):
            if self.stop.is_set():
                return
            if isinstance(action, Publish):
                self._publish_recorded(action)
            elif isinstance(action, Tick):
                tick = action.clock
                tick.lockstep = True
                tick.bounds = self._bounds(tick.bounds)
                self._tick_payload, self._tick_step = self._encoder.encode(tick), tick.step
                self._publish(keys.CLOCK, self._tick_payload)
                self.stats.ticks += 1
            elif isinstance(action, AwaitAck):
                self._wait_for_acks(action.step, [action.service])
            elif isinstance(action, AwaitAll):
                self._wait_for_acks(action.step)
            self._progress(tick)
        if self._tick_step is not None and not self.stop.is_set():
            self._wait_for_acks(self._tick_step)

    def _publish_recorded(self, action: Publish) -> None:
        payload = action.payload
        owner = keys.ack_owner(action.key)
        if owner is not None:  # a stand-in's acknowledgement: only the keys we replay are bounded
            ack = self._ack_decoder.decode(payload)
            kept = {k: v for k, v in ack.published.items() if self.replayed(k)}
            if kept != ack.published:
                ack.published = kept
                payload = self._encoder.encode(ack)
        elif action.sequence:
            self._published_seq[action.key] = action.sequence
        self._publish(action.key, payload)

    def _bounds(self, recorded: dict[str, int]) -> dict[str, int]:
        bounds = dict(self._published_seq)
        bounds.update((k, v) for k, v in recorded.items() if self.replayed(k))
        bounds.update(self.ledger.published(self.ledger.alive() - set(self._tokens)))
        return bounds

    def _wait_for_acks(self, step: int, names: list[str] | None = None) -> None:
        def under_test() -> list[str]:
            live = self.ledger.alive() - set(self._tokens)
            return sorted(live) if names is None else [n for n in names if n in live]

        silent = await_acks(self.ledger, step, under_test, self._wait_for_news, self._resend_tick, self.stop.is_set,
                            time.monotonic)
        if silent:
            self.stats.ack_timeouts += 1
            self.say(f"warning: tick {step}: no acknowledgement from {', '.join(silent)}; going on")

    def _wait_for_news(self, seconds: float) -> None:
        """Up to `seconds` for a token or an acknowledgement to come or go (cleared after the
        wait, before the caller looks again: nothing that came before the look is missed)."""
        if self._changed.wait(seconds):
            self._changed.clear()

    def _resend_tick(self) -> None:
        if self._tick_payload is not None:
            self._publish(keys.CLOCK, self._tick_payload, count=False)  # a service may have joined late
            self.stats.resent_ticks += 1
