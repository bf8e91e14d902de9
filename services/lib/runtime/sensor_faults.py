"""Sensor faults a sensor's own service acts on (scheduled by the simulator on falconry/sim/faults):
which one is in force at a mission time. Pure: the node feeds the commands and asks."""
from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class SensorFaults:
    kinds: tuple[str, ...]  # the fault kinds this sensor acts on
    windows: list[tuple[int, str, int | None]] = field(default_factory=list)  # (start ns, kind, end ns or None)

    def add(self, kind: str, start_ns: int, duration_s: float) -> None:
        """A fault from `start_ns` for `duration_s` seconds of mission time (0: until the end)."""
        if kind not in self.kinds:
            raise ValueError(f"not one of this sensor's faults ({', '.join(self.kinds)}): {kind!r}")
        end = start_ns + int(round(duration_s * 1e9)) if duration_s > 0 else None
        self.windows.append((int(start_ns), kind, end))

    def take(self, uav: str, fault) -> str | None:
        """A FaultCommand: added when it is for `uav` and of these kinds; returns what to log, or None."""
        if fault.uav != uav or fault.kind not in self.kinds:
            return None
        self.add(fault.kind, fault.header.stamp, fault.duration)
        return (f"{fault.kind} from {fault.header.stamp / 1e9:.2f} s"
                + (f" for {fault.duration:g} s" if fault.duration > 0 else " until the end"))

    def active(self, now_ns: int) -> str | None:
        """The most recently started fault in force at `now_ns`, or None."""
        live = [(start, i, kind) for i, (start, kind, end) in enumerate(self.windows)
                if start <= now_ns and (end is None or now_ns < end)]
        return max(live)[2] if live else None
