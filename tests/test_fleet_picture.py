"""The fleet picture end to end: a drone in uav2's working area that only uav1 sees (uav2's LiDAR
returns nothing the whole run, its detector still beats) is engaged and captured by uav2, from
the partner's track its own tracker joined into its picture (services/tracker/fleet.py)."""
from __future__ import annotations

import subprocess

import pytest

from tests.conftest import falconry_argv
from tests.tools.run import processes_mentioning, read_summary

SCENARIO = """name = "fleet"
duration = 35.0
seed = 1
uavs = 2
min_height = 1.0
max_height = 15.0
arena = [[0.0, 0.0], [80.0, 0.0], [80.0, 40.0], [0.0, 40.0]]  # uav1: x 0-40, uav2: x 40-80
starts = [[34.0, 20.0, 0.0], [72.0, 20.0, 3.1416]]

[[drones]]  # 6-18 m from uav1's start, in uav2's half
name = "intruder"
path = "circle"
speed = 2.0
center = [52.0, 20.0, 6.0]
radius = 6.0

[[faults]]  # every return of uav2's LiDAR is 'no return' (NaN): it sees nothing, its heartbeat goes on
time = 0.0
kind = "lidar_nan"
uav = "uav2"
duration = 1000.0
"""


@pytest.mark.heavy  # a 35 s mission beyond make test's 15-minute budget: make acceptance (the fleet logic's
@pytest.mark.timeout(300)  # unit tests, tests/test_tracker_fleet.py and the job manager's, run in make test)
def test_a_drone_only_uav1_sees_in_uav2s_area_is_captured_by_uav2(tmp_path, port):
    scenario = tmp_path / "fleet.toml"
    scenario.write_text(SCENARIO)
    summary_path = tmp_path / "summary.json"
    result = subprocess.run(falconry_argv("sim", str(scenario), "--lockstep", "--detector", "oracle", "--port", str(port),
                                          "--quiet", "--progress", "0", "--summary-json", str(summary_path),
                                          "--wall-timeout", "240"),
                            capture_output=True, text=True, timeout=280)
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-3000:]
    assert processes_mentioning(f":{port}") == [], "the run left processes behind"
    summary = read_summary(summary_path)
    uav1, uav2 = summary["uavs"]["uav1"], summary["uavs"]["uav2"]
    print(f"uav2's states: {uav2['states']}; captured: {summary['destroyed']}")
    assert summary["first_detected"]["intruder"]["by"] == "uav1"
    assert uav2["detections"] == 0  # uav2 never saw it itself
    assert "GOING_TO_TARGET" in [state for _, state in uav2["states"]]
    assert [e["target"] for e in uav2["engagements"]] == ["intruder"] and uav1["engagements"] == []
    [capture] = summary["destroyed"]
    assert capture["target"] == "intruder" and capture["by"] == "uav2", summary["destroyed"]
