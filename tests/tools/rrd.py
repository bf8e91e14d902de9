"""Reading rerun recordings back in tests: which entities hold data, at which mission times."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from rerun.chunk import RrdReader

RERUN = str(Path(sys.executable).parent / "rerun")


def entity_times(path: str | Path) -> dict[str, set[int]]:
    """Entity path (without the leading '/') -> the mission times (ns) it has data at; static
    entities map to {-1}. Blueprint and property entities are left out."""
    out: dict[str, set[int]] = {}
    for chunk in RrdReader(str(path)).stream():
        entity = chunk.entity_path.lstrip("/")
        if entity.startswith("__"):
            continue
        times = out.setdefault(entity, set())
        if chunk.is_static:
            times.add(-1)
        else:
            times.update(t.value for t in chunk.to_record_batch().column("mission_time") if t.is_valid)
    return out


def family_times(entities: dict[str, set[int]], family: str) -> set[int]:
    """Mission times with data anywhere at or under `family` (e.g. uav1/map/occupied)."""
    times: set[int] = set()
    for entity, at in entities.items():
        if entity == family or entity.startswith(family + "/"):
            times |= at
    return times


def verify(path: str | Path) -> subprocess.CompletedProcess:
    """`rerun rrd verify FILE` (exit 0 when the current rerun loads it)."""
    return subprocess.run([RERUN, "rrd", "verify", str(path)], capture_output=True, text=True, timeout=120)
