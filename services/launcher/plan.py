"""Which processes a `falconry sim` run starts, with which command lines and Zenoh settings."""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field

from schemas.keys import uav_services
from services.launcher.netns import UavNetwork
from services.runtime.zenoh_config import ZenohSettings


@dataclass
class RunPlan:
    hub_settings: ZenohSettings
    hub_label: str
    children: dict[str, list[str]] = field(default_factory=dict)  # name -> argv
    viewer: list[str] | None = None  # argv of `falconry view` drawing the run (--viz / --rrd)


def plan_run(args: argparse.Namespace, uavs: list[str], seed: int, duration: float, port: int,
             network: UavNetwork | None) -> RunPlan:
    embedded = args.zenoh_profile == "embedded" and not args.zenoh_config
    loopback_hub = f"tcp/127.0.0.1:{port}"
    if embedded:
        listen = [loopback_hub] + ([f"tcp/{network.host_address}:{port}"] if network else [])
        hub_label = " and ".join(listen)
    else:
        listen, hub_label = list(args.listen), args.zenoh_profile
    hub_settings = ZenohSettings(profile=args.zenoh_profile, connect=list(args.connect), listen=listen,
                                 config_file=args.zenoh_config, lease_ms=args.lease_ms,
                                 # the launcher carries no bulk data, and its process-wide segments
                                 # would outlive the run's clean-up
                                 shared_memory=False)

    def zenoh_args(connect: str, listen_on: str | None) -> list[str]:
        return ZenohSettings(profile=args.zenoh_profile, connect=[connect] if embedded else list(args.connect),
                             listen=[listen_on] if (embedded and listen_on) else [],
                             config_file=args.zenoh_config, lease_ms=args.lease_ms).as_args()

    base = [sys.executable, "-m", "services.launcher", "--log-level", args.log_level, "run"]
    extra = ["--exit-with-parent"] + (["--config", args.config] if args.config else [])
    plan = RunPlan(hub_settings, hub_label)
    # Root-namespace processes listen on the bridge too, so processes in a UAV's namespace reach them.
    sim_listen = f"tcp/{network.host_address}:0" if network else None
    plan.children["sim/simulator"] = base + [
        "simulator", *extra, *zenoh_args(loopback_hub, sim_listen), "--scenario", args.scenario,
        "--uavs", str(len(uavs)), "--seed", str(seed), "--duration", str(duration), "--rtf", str(args.rtf),
        "--tick", str(args.tick), "--detector", args.detector] + (["--lockstep"] if args.lockstep else [])
    for uav in uavs:
        for service in uav_services(args.detector):
            if network:
                argv = base + [service, "--uav", uav, *extra,
                               *zenoh_args(f"tcp/{network.host_address}:{port}", f"tcp/{network.address(uav)}:0")]
                argv = network.wrap(uav, argv)
            else:
                argv = base + [service, "--uav", uav, *extra, *zenoh_args(loopback_hub, None)]
            plan.children[f"{uav}/{service}"] = argv
    if args.viz or args.rrd:
        # a plain subscriber in the root namespace, never a lockstep participant
        plan.viewer = [sys.executable, "-m", "services.launcher", "--log-level", args.log_level, "view",
                       "--exit-with-parent", "--quiet", *zenoh_args(loopback_hub, None)] \
            + (["--rrd", args.rrd] if args.rrd else []) + (["--viz", args.viz] if args.viz else [])
    return plan
