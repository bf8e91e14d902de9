"""Whole missions (seed 004 ch. 3 & 5) on the oracle detector, in lockstep: revenge mode after a
partner is killed or cut off, the area split among three UAVs, and the abort system."""
from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from services.launcher import netns
from services.simulator.scenario import SCENARIO_DIR
from tests.conftest import falconry_argv
from tests.tools.run import processes_mentioning, read_summary

PARTNER_TIMEOUT = 15.0  # t_s, the job manager's default


def run_mission(tmp_path: Path, port: int, faults: str, *, uavs: int, duration: float, seed: int = 1,
                lease_ms: int | None = None) -> tuple[dict, str]:
    scenario = tmp_path / "mission.toml"
    scenario.write_text((SCENARIO_DIR / "mbzirc.toml").read_text() + faults)
    summary = tmp_path / "summary.json"
    argv = ["sim", str(scenario), "--uavs", str(uavs), "--lockstep", "--seed", str(seed), "--duration", str(duration),
            "--detector", "oracle", "--port", str(port), "--quiet", "--progress", "0", "--summary-json", str(summary),
            "--wall-timeout", "400"]
    if lease_ms:
        argv += ["--lease-ms", str(lease_ms)]
    result = subprocess.run(falconry_argv(*argv), capture_output=True, text=True, timeout=480)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-3000:]
    assert processes_mentioning(f":{port}") == [], "the run left processes behind"
    return read_summary(summary), result.stdout


def balloons_destroyed(summary: dict) -> list[float]:
    return sorted(d["t"] for d in summary["destroyed"] if d["kind"] == "balloon")


def took_over(summary: dict, uav: str, x: tuple[float, float], fallen: str) -> float | None:
    """Mission time at which `uav` reported the working area x-range `x` with `fallen` fallen."""
    for change in summary["team_changes"]:
        if change["uav"] == uav and fallen in change["fallen"] and tuple(change["x"]) == x:
            return change["t"]
    return None


def check_revenge(summary: dict, output: str, cut_at: float) -> None:
    took = took_over(summary, "uav1", (0.0, 100.0), "uav2")
    assert took is not None, summary["team_changes"]
    assert cut_at <= took <= cut_at + PARTNER_TIMEOUT + 1.0, f"uav1 took the whole arena at t={took}"
    destroyed = balloons_destroyed(summary)
    print(f"uav1 took the whole arena at t={took:.1f} s; balloons destroyed at {destroyed}")
    assert len(destroyed) == 5, output[-3000:]
    assert "uav1" in [d["by"] for d in summary["destroyed"] if d["t"] > took]


@pytest.mark.timeout(600)
def test_revenge_after_the_partner_is_killed(tmp_path, port):
    faults = '\n[[faults]]\ntime = 20.0\nkind = "kill"\nuav = "uav2"\n'
    summary, output = run_mission(tmp_path, port, faults, uavs=2, duration=120)
    check_revenge(summary, output, 20.0)


@pytest.mark.timeout(600)
@pytest.mark.skipif(netns.available() is not None, reason=f"link_cut needs {netns.available()}")
def test_revenge_after_the_link_to_the_partner_is_cut(tmp_path, port):
    faults = '\n[[faults]]\ntime = 20.0\nkind = "link_cut"\nuav = "uav2"\n'
    summary, output = run_mission(tmp_path, port, faults, uavs=2, duration=120, lease_ms=1000)
    check_revenge(summary, output, 20.0)
    assert netns.leftovers(f"f{port}") == []


@pytest.mark.timeout(600)
def test_silent_lidar_lands_that_uav_only_and_three_uavs_share_its_area(tmp_path, port):
    faults = '\n[[faults]]\ntime = 10.0\nkind = "lidar_silent"\nuav = "uav2"\nduration = 5.0\n'
    summary, output = run_mission(tmp_path, port, faults, uavs=3, duration=40)
    states = {name: [s for _, s in u["states"]] for name, u in summary["uavs"].items()}
    emergency = [t for t, s in summary["uavs"]["uav2"]["states"] if s == "EMERGENCY_LANDING"]
    assert emergency and 11.0 <= emergency[0] <= 11.5, summary["uavs"]["uav2"]["states"]
    assert summary["uavs"]["uav2"]["landed_s"] is not None and states["uav2"][-1] == "LANDED"
    for name in ("uav1", "uav3"):
        assert "EMERGENCY_LANDING" not in states[name], (name, states[name])
        assert summary["uavs"][name]["landed_s"] is None or summary["uavs"][name]["landed_s"] > 24.0
    left, right = took_over(summary, "uav1", (0.0, 50.0), "uav2"), took_over(summary, "uav3", (50.0, 100.0), "uav2")
    assert left is not None and right is not None, summary["team_changes"]
    assert max(left, right) <= emergency[0] + 1.0
    print(f"uav2 emergency landing at t={emergency[0]:.2f} s; uav1 took x 0..50 at t={left:.1f} s, "
          f"uav3 x 50..100 at t={right:.1f} s")
