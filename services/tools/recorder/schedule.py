"""The order of a lockstep replay, rebuilt from the lockstep protocol itself. Pure: no Zenoh, no clocks.

A recording's file order is the order the recorder *received* messages in, and messages from
different publishers overtake each other on their way to it (a classifier's acknowledgement of
tick k can be filed before the sensor driver's, even before tick k itself). Replaying in file
order would then feed a service the next stage's output before its own input. The lockstep
bookkeeping in the recording says where each message really belongs:

- a message on key K with seq q belongs before tick k when q <= tick k's bounds[K]
  (what the simulator published before the tick, or what a service had acknowledged by k-1);
- a message of a service S we stand in for belongs to S's slot in tick k when q <= the
  `published[K]` of S's recorded acknowledgement of tick k;
- a message no bound covers (its key is in neither) keeps its place relative to the ticks.

Within tick k the slots follow the pipeline (a service after its upstream services): a stand-in's
messages then its acknowledgement go out in its slot; for any other service the replay waits for
its live acknowledgement of k (if it runs). Before each tick every live service is waited for.
At the first replayed tick the services under test are joining: see `_first_tick_plan`.
"""
from __future__ import annotations

from dataclasses import dataclass
from itertools import takewhile
from typing import Iterable, Iterator, Union

import msgspec

from schemas import keys
from schemas.messages import SimClock, StepAck
from services.tools.recorder.mcap_io import RecordedMessage, header_of


@dataclass(frozen=True)
class Publish:
    key: str
    payload: bytes
    sequence: int = 0


@dataclass(frozen=True)
class Tick:
    clock: SimClock  # as recorded; the replayer sets its bounds
    payload: bytes


@dataclass(frozen=True)
class AwaitAck:
    service: str  # "uav1/classifier": wait for its acknowledgement of `step` if it is live
    step: int


@dataclass(frozen=True)
class AwaitAll:
    step: int  # wait for every live service's acknowledgement of `step`


Action = Union[Publish, Tick, AwaitAck, AwaitAll]


@dataclass
class _Pending:
    index: int  # position in the file
    msg: RecordedMessage
    sender: str


class LockstepSchedule:
    """Turns recorded messages (file order: the clock, every acknowledgement, the replayed data)
    into replay actions. `pipeline` lists services upstream first; `stand_ins` are the
    "scope/service" names whose recorded output is replayed on their behalf."""

    def __init__(self, stand_ins: Iterable[str], pipeline: Iterable[str], lookahead_ticks: int = 2) -> None:
        self.stand_ins = set(stand_ins)
        self.pipeline = list(pipeline)
        self.lookahead = lookahead_ticks
        self._clock_decoder = msgspec.msgpack.Decoder(SimClock)
        self._ack_decoder = msgspec.msgpack.Decoder(StepAck)
        self._ticks: dict[int, tuple[int, SimClock, bytes]] = {}
        self._done_steps: set[int] = set()
        self._acks: dict[tuple[str, int], tuple[StepAck, RecordedMessage]] = {}  # (owner, step)
        self._pending: list[_Pending] = []
        self._scopes: dict[str, set[str]] = {}  # UAV scope -> services seen acknowledging there
        self._last_step: int | None = None

    def _rank(self, service: str) -> int:
        return self.pipeline.index(service) if service in self.pipeline else len(self.pipeline)

    def actions(self, messages: Iterable[RecordedMessage]) -> Iterator[Action]:
        for index, msg in enumerate(messages):
            self._take(index, msg)
            while (step := self._next_step()) is not None and max(self._ticks) >= step + self.lookahead:
                yield from self._tick(step)
        while (step := self._next_step()) is not None:
            yield from self._tick(step)
        for item in self._pending:  # after the last tick: nothing bounds them any more
            yield Publish(item.msg.key, item.msg.payload, item.msg.sequence)
        self._pending = []

    def _take(self, index: int, msg: RecordedMessage) -> None:
        parts = msg.key.split("/")
        if len(parts) >= 3 and parts[1] != keys.SIM:
            self._scopes.setdefault(parts[1], set())
        if msg.key == keys.CLOCK:
            clock = self._clock_decoder.decode(msg.payload)
            if clock.step not in self._ticks and clock.step not in self._done_steps:  # re-sent ticks: once
                self._ticks[clock.step] = (index, clock, msg.payload)
            return
        owner = keys.ack_owner(msg.key)
        if owner is not None:
            scope, service = owner.split("/")
            if scope != keys.SIM:
                self._scopes.setdefault(scope, set()).add(service)
            ack = self._ack_decoder.decode(msg.payload)
            self._acks.setdefault((owner, ack.step), (ack, msg))
            return
        header = header_of(msg.payload)
        self._pending.append(_Pending(index, msg, header.sender if header is not None else ""))

    def _next_step(self) -> int | None:
        return min(self._ticks) if self._ticks else None

    def _tick(self, step: int) -> Iterator[Action]:
        clock_index, clock, payload = self._ticks.pop(step)
        self._done_steps.add(step)
        next_index = self._ticks[min(self._ticks)][0] if self._ticks else None
        before: list[_Pending] = []
        slots: dict[str, list[_Pending]] = {}
        keep: list[_Pending] = []
        for item in self._pending:
            place = self._place(item, step, clock, clock_index, next_index)
            if place == "before":
                before.append(item)
            elif place is None:
                keep.append(item)
            else:
                slots.setdefault(place, []).append(item)
        self._pending = keep

        first = self._last_step is None
        if not first:
            yield AwaitAll(self._last_step)
        self._last_step = step
        for item in before:
            yield Publish(item.msg.key, item.msg.payload, item.msg.sequence)
        order = self._slot_order()
        early = self._first_tick_plan(order) if first else []
        for name in early:
            yield from self._slot(name, step, slots)
        yield Tick(clock, payload)
        for name in order:
            if name not in self.stand_ins:
                yield AwaitAck(name, step)
            elif name not in early:
                yield from self._slot(name, step, slots)
        for items in slots.values():  # stand-ins in no UAV scope (none today): after the pipeline
            for item in items:
                yield Publish(item.msg.key, item.msg.payload, item.msg.sequence)
        for old in [k for k in self._acks if k[1] <= step]:
            del self._acks[old]

    def _slot_order(self) -> list[str]:
        """Every (scope, service) slot of a tick: upstream services first, UAV by UAV within a stage."""
        services = set(self.pipeline).union(*self._scopes.values())
        return [f"{scope}/{service}" for service in sorted(services, key=lambda s: (self._rank(s), s))
                for scope in sorted(self._scopes)]

    def _slot(self, name: str, step: int, slots: dict[str, list[_Pending]]) -> Iterator[Publish]:
        for item in slots.pop(name, []):
            yield Publish(item.msg.key, item.msg.payload, item.msg.sequence)
        recorded = self._acks.get((name, step))
        if recorded is not None:
            yield Publish(recorded[1].key, recorded[1].payload)

    def _first_tick_plan(self, order: list[str]) -> list[str]:
        """Stand-in slots delivered before the first replayed tick. A service joins the replay at
        that tick: at step 0 it waits for its upstream like at any tick, but joining later (a
        recording started mid-run) it waits for nothing and takes what it holds. Sending the
        output of the stand-ins at the head of each UAV's pipeline first makes the service after
        them use it in that tick either way, as it did in the recorded run."""
        early: list[str] = []
        for scope in sorted(self._scopes):
            names = [n for n in order if n.split("/")[0] == scope]
            lead = list(takewhile(lambda n: n in self.stand_ins, names))
            if len(lead) < len(names):  # somebody to feed
                early += lead
        return early

    def _place(self, item: _Pending, step: int, clock: SimClock, clock_index: int, next_index: int | None):
        """'before' the tick, a stand-in's name (its slot in this tick), or None (a later tick)."""
        key, seq = item.msg.key, item.msg.sequence
        bounded = False
        bound = clock.bounds.get(key)
        if bound is not None:
            bounded = True
            if 0 < seq <= bound:
                return "before"
        if item.sender in self.stand_ins:
            ack = self._acks.get((item.sender, step))
            if ack is not None and key in ack[0].published:
                bounded = True
                if 0 < seq <= ack[0].published[key]:
                    return item.sender
        if bounded and seq > 0:
            return None
        if item.index < clock_index:
            return "before"
        if item.sender in self.stand_ins and (next_index is None or item.index < next_index):
            return item.sender
        return None
