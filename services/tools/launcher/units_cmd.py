"""`falconry units DIR`: write the onboard systemd units (services/tools/launcher/systemd_units.py)."""
from __future__ import annotations

import argparse
import re
from pathlib import Path

from schemas import keys
from services.tools.launcher.common import CliError
from services.tools.launcher.systemd_units import DEFAULT_PREFIX, TARGET_UNIT, USER, UnitSettings, render_units


SYSTEM_UNITS = Path("/etc/systemd/system")
ONBOARD_DETECTORS = [d for d in keys.DETECTORS if d != keys.ORACLE]  # the oracle reads ground truth
ACCOUNT = re.compile(r"^[a-z_][a-z0-9_-]*$")  # what useradd accepts by default


def add_parser(commands) -> None:
    p = commands.add_parser(
        "units", help="write the systemd units that run a UAV's services onboard",
        description="Write one systemd template unit per per-UAV service (instance = the UAV, e.g. "
                    "falconry-tracker@uav1), one for the UAV's Zenoh router and falconry@.target, which starts "
                    "them all. Install them in /etc/systemd/system and run `systemctl enable --now "
                    "falconry@uav1.target` (docs/deploy.md has every step).")
    p.add_argument("dir", metavar="DIR", help="where to write the units (created if missing)")
    p.add_argument("--prefix", default=DEFAULT_PREFIX, metavar="VENV",
                   help=f"the virtual environment falconry is installed in (default {DEFAULT_PREFIX})")
    p.add_argument("--detector", choices=ONBOARD_DETECTORS, default=keys.DEFAULT_DETECTOR,
                   help="which per-UAV services to run, as `falconry sim --detector` (default %(default)s)")
    p.add_argument("--positioning", choices=keys.POSITIONING, default="gnss",
                   help="where the UAV's position comes from, as `falconry sim --positioning`: lidar (no "
                        "GNSS) adds the localizer's unit, whose estimate the flight controller bridge flies on "
                        "(default %(default)s)")
    p.add_argument("--user", default=USER, help="the account the services run as (default %(default)s)")
    p.set_defaults(handler=run_units)


def run_units(args: argparse.Namespace) -> int:
    if not ACCOUNT.match(args.user):
        raise CliError(f"--user {args.user!r}: an account name is lower-case letters, digits, '_' and '-'")
    if not args.prefix.startswith("/"):
        raise CliError(f"--prefix {args.prefix!r}: systemd needs an absolute path")
    out = Path(args.dir)
    if out.exists() and not out.is_dir():
        raise CliError(f"{out} exists and is not a directory")
    out.mkdir(parents=True, exist_ok=True)
    units = render_units(UnitSettings(prefix=args.prefix.rstrip("/"), detector=args.detector, user=args.user,
                                      positioning=args.positioning))
    for name, text in units.items():
        (out / name).write_text(text)
    print(f"wrote {len(units)} units to {out}: {', '.join(sorted(units))}")
    install = "" if out.resolve() == SYSTEM_UNITS else f"cp {out}/* {SYSTEM_UNITS}/ && "
    print(f"next: {install}systemctl daemon-reload && systemctl enable --now {TARGET_UNIT.replace('@.', '@uav1.')}")
    return 0
