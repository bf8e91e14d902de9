"""Carries out the process and link faults the simulator announces on falconry/sim/faults:
`kill` (SIGKILL; one service is restarted by supervision as usual, a whole UAV stays down
for the fault's duration, or for good), `freeze` (SIGSTOP, SIGCONT when it ends),
`link_cut` (the UAV's veth goes down; needs the run's per-UAV network namespaces) and
`router_restart` (the run's own Zenoh router is killed and started again after the fault's
duration; its clients reconnect by themselves). LiDAR faults belong to the sensor driver,
odometry jumps to the simulator, and duplicate, reorder, slow and clock_jump to every
service's runtime."""
from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from typing import Callable

from schemas import keys
from schemas.messages import FaultCommand
from services.tools.launcher import netns
from services.tools.launcher.netns import UavNetwork
from services.tools.launcher.supervisor import Supervisor

PROCESS_FAULTS = ("kill", "freeze", "link_cut", "router_restart")
ROUTER = "sim/router"  # the run's own router, a child of the launcher like the services


@dataclass
class ActiveFault:
    command: FaultCommand
    ends_at: float | None  # mission time, s; None = until the end of the run
    targets: list[str]
    ends_wall: float | None = None  # time.monotonic() instead, for a fault that stops mission time reaching us


class FaultExecutor:
    def __init__(self, supervisor: Supervisor, network: UavNetwork | None,
                 report: Callable[[str, str, str], None]) -> None:
        self.supervisor = supervisor
        self.network = network
        self.report = report  # (kind, subject, detail) -> an event in the run's log
        self.active: list[ActiveFault] = []

    def targets(self, command: FaultCommand) -> list[str]:
        if command.kind == "router_restart":
            return [ROUTER] if ROUTER in self.supervisor.children else []
        services = [command.service] if command.service else [s for s in keys.SERVICES if s not in keys.SIM_SERVICES]
        return [name for s in services if (name := f"{command.uav}/{s}") in self.supervisor.children]

    def start(self, command: FaultCommand, mission_time: float) -> None:
        if command.kind not in PROCESS_FAULTS:
            return
        targets = self.targets(command)
        ends_at = mission_time + command.duration if command.duration > 0 else None
        subject = "/".join(filter(None, (command.uav, command.service))) or "router"
        if command.kind == "router_restart":
            if not targets:
                self.report("fault_failed", subject, "router_restart needs the run's own router (--zenoh-profile router)")
                return
            # while the router is down no clock tick reaches the launcher: the downtime is wall time
            self.supervisor.kill(ROUTER, hold=True)
            self.active.append(ActiveFault(command, None, targets, ends_wall=time.monotonic() + command.duration))
            self.report("fault_started", subject, f"router_restart: router down for {command.duration:g} s of wall time")
            return
        elif command.kind == "kill":
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
        now = time.monotonic()
        for fault in [f for f in self.active if (f.ends_at is not None and mission_time >= f.ends_at)
                      or (f.ends_wall is not None and now >= f.ends_wall)]:
            self.end(fault)

    def end(self, fault: ActiveFault) -> None:
        self.active.remove(fault)
        command = fault.command
        if command.kind in ("kill", "router_restart"):
            for name in fault.targets:
                self.supervisor.release(name)
        elif command.kind == "freeze":
            for name in fault.targets:
                self.supervisor.send(name, signal.SIGCONT)
        elif command.kind == "link_cut" and self.network is not None:
            self.network.restore(command.uav)
        self.report("fault_ended", "/".join(filter(None, (command.uav, command.service))) or "router", command.kind)

    def end_all(self) -> bool:
        """Before shutdown: frozen processes must be able to take SIGTERM, links and the router
        come back. True when a link or the router was restored (its clients need a moment)."""
        restored = False
        for fault in list(self.active):
            if fault.command.kind in ("freeze", "link_cut", "router_restart"):
                restored |= fault.command.kind in ("link_cut", "router_restart")
                self.end(fault)
        return restored
