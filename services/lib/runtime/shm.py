"""Zenoh shared-memory segments left behind by processes that have ended.

Zenoh moves large local messages through files in /dev/shm. A process that ends
(cleanly or not) can leave its segment behind, and Zenoh deletes such orphans only when
a later shared-memory session starts. Whoever supervises processes (the launcher, a
test, a benchmark) applies Zenoh's own rule once its children are gone: a segment no
process holds open or mapped is an orphan, and is removed.
"""
from __future__ import annotations

import os
from pathlib import Path

SHM_DIR = Path("/dev/shm")


def segments() -> set[Path]:
    """Zenoh segments of this user (another user's are not ours to judge or remove)."""
    if not SHM_DIR.is_dir():
        return set()
    uid = os.getuid()
    return {p for p in SHM_DIR.glob("*zenoh*") if _owner(p) == uid}


def _owner(path: Path) -> int | None:
    try:
        return path.stat().st_uid
    except OSError:
        return None


def in_use() -> set[str]:
    """Paths of /dev/shm files some process has open or mapped."""
    held: set[str] = set()
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            for fd in os.listdir(proc / "fd"):
                try:
                    target = os.readlink(proc / "fd" / fd)
                except OSError:
                    continue
                if target.startswith("/dev/shm/"):
                    held.add(target)
            with open(proc / "maps") as maps:
                for line in maps:
                    if "/dev/shm/" in line:
                        held.add(line[line.index("/dev/shm/"):].split()[0])
        except OSError:
            continue  # a process that just ended, or one we may not look into
    return held


def orphans(among: set[Path] | None = None) -> set[Path]:
    candidates = segments() if among is None else among
    if not candidates:
        return set()
    held = in_use()
    return {p for p in candidates if str(p) not in held and p.exists()}


def remove_orphans(among: set[Path] | None = None) -> list[str]:
    removed = []
    for path in sorted(orphans(among)):
        try:
            path.unlink()
            removed.append(path.name)
        except OSError:
            pass  # gone already, or not ours to remove
    return removed
