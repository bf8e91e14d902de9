"""`falconry run SERVICE`: one service alone, as compose and onboard deployment start it."""
from __future__ import annotations

import argparse

from schemas import keys
from services.simulator.options import add_simulator_options
from services.tools.launcher.common import EXIT_CODES, FOREVER, CliError, add_zenoh_options, zenoh_settings
from services.tools.launcher.params import ParamsError, params_for
from services.tools.registry import node_class


def add_parser(commands) -> None:
    p = commands.add_parser(
        "run", help="run one service in this process",
        description="Run one service alone (what compose and onboard deployment use). Every per-UAV "
                    "service needs --uav; the simulator is run-wide. A Zenoh that does not answer yet (a router "
                    "started after the service) is retried with back-off, one log line per attempt, until it "
                    "answers or --connect-timeout runs out.",
        epilog=EXIT_CODES,
    )
    p.add_argument("service", choices=keys.SERVICES, metavar="SERVICE",
                   help="one of: " + ", ".join(keys.SERVICES))
    p.add_argument("--uav", help="UAV this service belongs to, e.g. uav1 (required except for the simulator)")
    p.add_argument("--config", metavar="FILE", help="TOML parameters, one [service] table each")
    p.add_argument("--clock", choices=["sim", "wall"], default="sim",
                   help="sim: follow the simulator's mission clock (default); wall: system time, for onboard runs")
    p.add_argument("--tick-hz", type=float, default=20.0, help="tick rate with --clock wall (default 20)")
    p.add_argument("--simulated-faults", choices=["auto", "on", "off"], default="auto",
                   help="obey the simulator's fault commands (falconry/sim/faults: duplicated, reordered or slowed "
                        "inputs, silenced partners and cut radios in lockstep, clock jumps). auto (default): on "
                        "with --clock sim (where it cannot be off), off with --clock wall, so a service onboard "
                        "never obeys one")
    p.add_argument("--exit-with-parent", action="store_true",
                   help="stop when the launching process dies (the launcher sets this)")
    add_zenoh_options(p, "Embedded default: none (this process only listens).", connect_timeout=FOREVER,
                      tls_identity=None)
    add_simulator_options(p)
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:

    cls = node_class(args.service)
    if args.service not in keys.SIM_SERVICES:
        if not args.uav:
            raise CliError(f"{args.service} is a per-UAV service: give --uav (e.g. --uav uav1)")
        try:
            keys.check_name(args.uav, "UAV name")
        except ValueError as exc:
            raise CliError(str(exc)) from None
    elif args.uav:
        raise CliError(f"{args.service} is run-wide: it takes no --uav")
    if args.tick_hz <= 0:
        raise CliError("--tick-hz must be positive")
    try:
        params = params_for(args.service, cls.params_type, args.config)
    except ParamsError as exc:
        raise CliError(str(exc)) from None
    if args.simulated_faults == "off" and args.clock == "sim":
        raise CliError("--simulated-faults off needs --clock wall: a service on the simulator's clock follows its "
                       "fault commands (in lockstep, which partners a fault silences or cuts off)")
    simulated_faults = {"auto": None, "on": True, "off": False}[args.simulated_faults]
    node = cls(args.uav, zenoh_settings(args), params=params, clock=args.clock, tick_hz=args.tick_hz,
               exit_with_parent=args.exit_with_parent, options=args, simulated_faults=simulated_faults)
    return node.run()
