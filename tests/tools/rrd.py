"""Reading rerun recordings back in tests: which entities hold data, at which mission times."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import rerun_cli
from rerun.chunk import RrdReader

RERUN = str(Path(sys.executable).parent / "rerun")
VIEWER_BINARY = str(Path(rerun_cli.__file__).parent / "rerun")  # the viewer itself, no Python wrapper
# The component of each archetype the viewer draws that says how many things a row holds.
CONTENT = (":positions", ":centers", ":strips", ":translation", ":text", ":state", ":scalars", ":vertex_positions",
           ":blob")


def entity_times(path: str | Path, with_content: bool = False) -> dict[str, set[int]]:
    """Entity path (without the leading '/') -> the mission times (ns) it has data at; static
    entities map to {-1}. Blueprint and property entities are left out. With `with_content`, a row
    counts only if it holds at least one thing (a point, a box, a line, a text ...), so an entity
    logged empty on a timer does not pass for one with data."""
    out: dict[str, set[int]] = {}
    for chunk in RrdReader(str(path)).stream():
        entity = chunk.entity_path.lstrip("/")
        if entity.startswith("__"):
            continue
        times = out.setdefault(entity, set())
        if chunk.is_static:
            times.add(-1)
            continue
        batch = chunk.to_record_batch()
        rows = range(batch.num_rows)
        if with_content:
            columns = [batch.column(name) for name in batch.schema.names if name.endswith(CONTENT)]
            rows = [r for r in rows if any(c[r].is_valid and len(c[r]) > 0 for c in columns)]
        stamps = batch.column("mission_time")
        times.update(stamps[r].value for r in rows if stamps[r].is_valid)
    return {entity: times for entity, times in out.items() if times}


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
