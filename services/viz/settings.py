"""The viewer's settings: how much it draws, and where it shows the recording.

Kept free of rerun and scipy, so the command line (every service starts through it) stays quick.
"""
from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from services.runtime.errors import UsageError

VIEWER_MODES = ("spawn", "web")  # or a rerun+http://HOST:PORT/proxy address
WEB_PORT = 9090
GRPC_PORT = 9876


@dataclass
class ViewParams:
    """How much the viewer draws (the rest of every message is drawn in full)."""

    scan_period: float = 0.5  # s of mission time between drawn scans of one UAV
    scan_points: int = 2000  # at most this many points per drawn scan (flying / unknown points always)
    map_period: float = 1.0  # s between map draws of one UAV (each draws only what changed)
    map_cell: int = 1  # map voxels per side of a drawn cube (2: 1 m cubes for 0.5 m voxels, a quarter the data)
    map_layers: int = 64  # drawn map layers per UAV before they fold into one
    pose_period: float = 0.1  # s between drawn poses of one UAV
    track_period: float = 0.2  # s between drawn track sets of one UAV
    truth_period: float = 0.2  # s between drawn true positions
    trail_period: float = 1.0  # s between redraws of trails and paths
    trail_spacing: float = 0.25  # s between the points of a trail or path
    trail_length: float = 60.0  # s of trail kept
    prediction_horizon: float = 3.0  # s of constant-acceleration prediction drawn per confirmed track
    ellipsoid_sigma: float = 2.0  # covariance ellipsoids at this many standard deviations
    status_period: float = 1.0  # s between redraws of status, working area and forbidden zones


def check_viewer(viewer: str) -> None:
    """One clear line for a viewer that cannot work here, before anything starts."""
    if viewer == "spawn":
        if not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")) and os.name == "posix" \
                and not _is_macos():
            raise UsageError("no display for a native viewer here: use --viz web (then open http://127.0.0.1:9090 "
                             "in a browser), --viz rerun+http://HOST:PORT/proxy for a viewer elsewhere, or --rrd FILE")
        if viewer_executable() is None:
            raise UsageError("the rerun viewer is not installed (pip install rerun-sdk)")
    elif viewer not in VIEWER_MODES and not viewer.startswith(("rerun://", "rerun+http://", "rerun+https://")):
        raise UsageError(f"--viz takes spawn, web or a viewer address such as rerun+http://127.0.0.1:9876/proxy, "
                         f"not {viewer!r}")


def _is_macos() -> bool:
    return os.uname().sysname == "Darwin"


def viewer_executable() -> str | None:
    """The rerun viewer binary: on the PATH, or the one the rerun-sdk wheel ships."""
    found = shutil.which("rerun")
    if found:
        return found
    try:
        import rerun_cli  # the wheel's viewer lives beside this module; light to import
    except ImportError:
        return None
    bundled = Path(rerun_cli.__file__).parent / "rerun"
    return str(bundled) if bundled.is_file() else None
