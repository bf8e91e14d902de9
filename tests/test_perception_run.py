"""Perception on a whole lockstep run (seed 000 sec. III-D, Fig. 4): the `takeoff` scenario's drone,
landed 0.5 m from a building's wall, is background while it stands there and climbs along the
wall, and is detected within 3 s once it is more than 2 m clear of the building (the
separate-cluster reset and the ray casting clear the voxels it leaves)."""
from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest

from services.simulator.scenario import load_scenario
from services.tools.launcher.monitor import read_truth_log
from tests.conftest import REPO, falconry_argv

CLEAR = 2.0  # m between the drone's body and the building
WITHIN = 3.0  # s


def gap_to_box(position, radius: float, center, size) -> float:
    low, high = np.asarray(center) - np.asarray(size) / 2, np.asarray(center) + np.asarray(size) / 2
    outside = np.maximum(np.maximum(low - position, 0.0), np.asarray(position) - high)
    return float(np.linalg.norm(outside)) - radius


@pytest.mark.slow(95)
def test_a_drone_taking_off_beside_a_wall_is_detected_within_3_s_once_2_m_clear(tmp_path, port):
    scenario = load_scenario("takeoff")
    building = next(o for o in scenario.obstacles if o.name == "building")
    (riser,) = scenario.drones
    summary, truth = tmp_path / "summary.json", tmp_path / "truth.log"
    run = subprocess.run(falconry_argv("sim", "takeoff", "--lockstep", "--duration", "54", "--port", str(port),
                                       "--detector", "classifier",  # the LiDAR perception is the subject
                                       "--quiet", "--progress", "0", "--summary-json", str(summary),
                                       "--truth-log", str(truth)),
                         cwd=REPO, capture_output=True, text=True, timeout=400)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]

    clear_at = None
    for ground_truth in read_truth_log(truth):
        t = ground_truth.header.stamp / 1e9
        drone = next(d for d in ground_truth.targets if d.id == riser.name)
        if t > riser.takeoff_time and gap_to_box(drone.position, drone.radius, building.center, building.size) > CLEAR:
            clear_at = t
            break
    assert clear_at is not None, "the drone never got 2 m clear of the building"

    result = json.loads(summary.read_text())
    first = result["first_detected"].get(riser.name)
    assert first is not None, "the drone was never detected"
    print(f"takeoff at {riser.takeoff_time:g} s, 2 m clear at {clear_at:.2f} s, first detected at {first['t']:.2f} s "
          f"by {first['by']}")
    assert riser.takeoff_time < first["t"] <= clear_at + WITHIN  # never while landed; soon once clear
    for name, uav in result["uavs"].items():  # and nothing else was taken for a flying object
        assert uav["perception"]["false"] == 0 and uav["perception"]["false_tracks"] == 0, (name, uav["perception"])
