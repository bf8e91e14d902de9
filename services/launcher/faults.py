"""Carries out the process and link faults the simulator announces on falconry/sim/faults:
`kill` (SIGKILL; one service is restarted by supervision as usual, a whole UAV stays down
for the fault's duration, or for good), `freeze` (SIGSTOP, SIGCONT when it ends) and
`link_cut` (the UAV's veth goes down; needs the run's per-UAV network namespaces).
LiDAR faults belong to the sensor driver and odometry jumps to the simulator."""
from __future__ import annotations

import signal
from dataclasses import dataclass
from typing import Callable

from schemas import keys
from schemas.messages import FaultCommand
from services.launcher import netns
from services.launcher.netns import UavNetwork
from services.launcher.supervisor import Supervisor

PROCESS_FAULTS = ("kill", "freeze", "link_cut")


@dataclass
class ActiveFault:
    command: FaultCommand
    ends_at: float | None  # mission time, s; None = until the end of the run
    targets: list[str]


class FaultExecutor:
    def __init__(self, supervisor: Supervisor, network: UavNetwork | None,
                 report: Callable[[str, str, str], None]) -> None:
        self.supervisor = supervisor
        self.network = network
        self.report = report  # (kind, subject, detail) -> an event in the run's log
        self.active: list[ActiveFault] = []

    def targets(self, command: FaultCommand) -> list[str]:
        services = [command.service] if command.service else list(keys.UAV_SERVICES) + [keys.ORACLE]
        return [name for s in services if (name := f"{command.uav}/{s}") in self.supervisor.children]

    def start(self, command: FaultCommand, mission_time: float) -> None:
        if command.kind not in PROCESS_FAULTS:
            return
        targets = self.targets(command)
        ends_at = mission_time + command.duration if command.duration > 0 else None
        subject = "/".join(filter(None, (command.uav, command.service)))
        if command.kind == "kill":
            whole_uav = not command.service
            for name in targets:
                self.supervisor.kill(name, hold=whole_uav)
            detail = "whole UAV down" + (f" for {command.duration:g} s" if ends_at else " for good") \
                if whole_uav else "supervisor restarts it"
        elif command.kind == "freeze":
            for name in targets:
                self.supervisor.send(name, signal.SIGSTOP)
            detail = f"SIGSTOP for {command.duration:g} s" if ends_at else "SIGSTOP for good"
        else:
            if self.network is None:
                self.report("fault_failed", subject, "link_cut needs per-UAV network namespaces")
                return
            try:
                self.network.cut(command.uav)
            except netns.NetnsError as exc:  # the veth may be down already: restore it at the end
                self.active.append(ActiveFault(command, ends_at, targets))
                self.report("fault_failed", subject, f"link_cut incomplete: {exc}")
                return
            detail = f"veth down for {command.duration:g} s" if ends_at else "veth down for good"
        self.active.append(ActiveFault(command, ends_at, targets))
        self.report("fault_started", subject, f"{command.kind}: {detail}")

    def tick(self, mission_time: float) -> None:
        for fault in [f for f in self.active if f.ends_at is not None and mission_time >= f.ends_at]:
            self.end(fault)

    def end(self, fault: ActiveFault) -> None:
        self.active.remove(fault)
        command = fault.command
        if command.kind == "kill":
            for name in fault.targets:
                self.supervisor.release(name)
        elif command.kind == "freeze":
            for name in fault.targets:
                self.supervisor.send(name, signal.SIGCONT)
        elif command.kind == "link_cut" and self.network is not None:
            self.network.restore(command.uav)
        self.report("fault_ended", "/".join(filter(None, (command.uav, command.service))), command.kind)

    def end_all(self) -> bool:
        """Before shutdown: frozen processes must be able to take SIGTERM, links come back.
        True when a link was restored."""
        restored = False
        for fault in list(self.active):
            if fault.command.kind in ("freeze", "link_cut"):
                restored |= fault.command.kind == "link_cut"
                self.end(fault)
        return restored
