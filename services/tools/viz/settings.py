"""The viewer's settings: how much it draws, and where it shows the recording.

Kept free of rerun and scipy, so the command line (every service starts through it) stays quick.
"""
from __future__ import annotations

import os
import shutil
import socket
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import quote, urlparse

from services.lib.runtime.errors import UsageError

VIEWER_MODES = ("spawn", "web")  # or a rerun+http://HOST:PORT/proxy address
WEB_PORT = 9090  # the web viewer's page
GRPC_PORT = 9876  # rerun's own default: a spawned viewer, or the server behind the web viewer
VIEWER_SCHEMES = ("rerun://", "rerun+http://", "rerun+https://")


def grpc_address(port: int = GRPC_PORT) -> str:
    return f"rerun+http://127.0.0.1:{port}/proxy"


def web_address(port: int = GRPC_PORT) -> str:
    """The web viewer's page, told where the recording is (the bare page shows rerun's welcome)."""
    return f"http://127.0.0.1:{WEB_PORT}/?url={quote(grpc_address(port), safe='')}"


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
            raise UsageError(f"no display for a native viewer here: use --viz web (a browser on port {WEB_PORT}), "
                             f"--viz rerun+http://HOST:PORT/proxy for a viewer elsewhere, or --rrd FILE")
        if viewer_executable() is None:
            raise UsageError("the rerun viewer is not installed (pip install rerun-sdk)")
    elif viewer != "web":
        if not viewer.startswith(VIEWER_SCHEMES):
            raise UsageError(f"--viz takes spawn, web or a viewer address such as {grpc_address()}, not {viewer!r}")
        where = urlparse(viewer.split("+", 1)[-1])
        try:
            socket.create_connection((where.hostname or "127.0.0.1", where.port or GRPC_PORT), timeout=2.0).close()
        except OSError:
            raise UsageError(f"no rerun viewer answers at {viewer} (start one there with `rerun`)") from None


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
