"""Which processes a `falconry sim` run starts, with which command lines and Zenoh settings."""
from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass, field

from schemas.keys import SIM, uav_services
from services.lib.runtime import tls
from services.lib.runtime.zenoh_config import ZenohSettings
from services.tools.launcher.netns import UavNetwork
from services.tools.launcher.supervisor import SERVICE_MODULE

SIMULATOR = f"{SIM}/simulator"  # the simulator's child name (its scope and service)


@dataclass
class RunPlan:
    hub_settings: ZenohSettings
    hub_label: str
    children: dict[str, list[str]] = field(default_factory=dict)  # name -> argv
    router: list[str] | None = None  # argv of the run's own Zenoh router (router profile without --connect)
    viewer: list[str] | None = None  # argv of `falconry view` drawing the run (--viz / --rrd)


OWN_ROUTER_TIMEOUT_S = 20.0


def own_router_wanted(args: argparse.Namespace) -> bool:
    """The router profile with no router named: the run brings its own."""
    return args.zenoh_profile == "router" and not args.connect and not args.zenoh_config


def plan_run(args: argparse.Namespace, uavs: list[str], seed: int, duration: float, port: int,
             network: UavNetwork | None, positioning: dict[str, str] | None = None) -> RunPlan:
    """`positioning`: UAV -> "gnss" or "lidar" (the scenario's, or --positioning; default gnss): a
    UAV flying without GNSS runs a localizer too."""
    embedded = args.zenoh_profile == "embedded" and not args.zenoh_config
    # --tls: every link is mutual TLS, each child presenting its own identity (derived from its
    # command line); the run's own router then also enforces the team's access control
    tls_dir = getattr(args, "tls", None) or None
    loopback_hub = f"{'tls' if tls_dir else 'tcp'}/127.0.0.1:{port}"
    own_router = own_router_wanted(args)
    connect = [loopback_hub] if own_router else list(args.connect)
    if embedded:
        listen = [loopback_hub] + ([f"tcp/{network.host_address}:{port}"] if network else [])
        hub_label = " and ".join(listen)
    elif own_router:
        listen, hub_label = [], f"router {loopback_hub} (the run's own, `falconry router`)"
    else:
        listen, hub_label = list(args.listen), args.zenoh_profile
    hub_settings = ZenohSettings(profile=args.zenoh_profile, connect=connect, listen=listen,
                                 config_file=args.zenoh_config, lease_ms=args.lease_ms,
                                 # the launcher carries no bulk data, and its process-wide segments
                                 # would outlive the run's clean-up
                                 shared_memory=False,
                                 # an embedded hub only listens: a busy --port is one clear error, not a wait;
                                 # our own router is up in a second, or it failed (a busy port)
                                 connect_timeout=0 if embedded else OWN_ROUTER_TIMEOUT_S if own_router else None,
                                 tls_dir=tls_dir, tls_identity=tls.SIM if tls_dir else None)

    def zenoh_args(connect: list[str], listen: list[str], gossip_connect: bool = True) -> list[str]:
        return ZenohSettings(profile=args.zenoh_profile, connect=connect if embedded or own_router else list(args.connect),
                             listen=listen if embedded else [], config_file=args.zenoh_config,
                             lease_ms=args.lease_ms, gossip_connect=gossip_connect, tls_dir=tls_dir).as_args()

    base = [sys.executable, "-m", SERVICE_MODULE, "--log-level", args.log_level, "run"]
    extra = ["--exit-with-parent"] + (["--config", args.config] if args.config else [])
    plan = RunPlan(hub_settings, hub_label)
    if own_router:
        plan.router = [sys.executable, "-m", "services.tools.launcher", "--log-level", args.log_level, "router",
                       "--exit-with-parent", "--listen", loopback_hub] \
            + (["--tls", tls_dir, "--team", ",".join(uavs)] if tls_dir else [])
    # With namespaces, the simulator is reached by each UAV over that UAV's airframe link only (never
    # over the radio bridge, which a link_cut takes down), and by the ground over loopback.
    sim_listen = ["tcp/127.0.0.1:0"] + [f"tcp/{network.sim_address(u)}:{port}" for u in uavs] if network else []
    plan.children[SIMULATOR] = base + [
        "simulator", *extra, *zenoh_args([loopback_hub], sim_listen, gossip_connect=network is None),
        "--scenario", args.scenario,
        "--uavs", str(len(uavs)), "--seed", str(seed), "--duration", str(duration), "--rtf", str(args.rtf),
        "--tick", str(args.tick), "--detector", args.detector] + (["--lockstep"] if args.lockstep else []) \
        + (["--positioning", args.positioning] if getattr(args, "positioning", None) else [])
    for uav in uavs:
        for service in uav_services(args.detector, (positioning or {}).get(uav, "gnss")):
            if network:  # the ground and the partners over the radio, the simulator over the airframe link
                connect = [f"tcp/{network.host_address}:{port}", f"tcp/{network.sim_address(uav)}:{port}"]
                argv = base + [service, "--uav", uav, *extra, *zenoh_args(connect, [f"tcp/{network.address(uav)}:0"])]
                argv = network.wrap(uav, argv)
            else:
                argv = base + [service, "--uav", uav, *extra, *zenoh_args([loopback_hub], [])]
            plan.children[f"{uav}/{service}"] = argv
    if args.viz or args.rrd:
        # a plain subscriber in the root namespace, never a lockstep participant
        plan.viewer = [sys.executable, "-m", "services.tools.launcher", "--log-level", args.log_level, "view",
                       "--exit-with-parent", "--quiet", *zenoh_args([loopback_hub], [])] \
            + (["--rrd", args.rrd] if args.rrd else []) + (["--viz", args.viz] if args.viz else [])
    return plan
