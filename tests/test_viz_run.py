"""The fleet viewer on whole runs: `falconry sim --rrd/--viz/--plot` and `falconry view RUN.mcap`.

One lockstep mission is drawn three ways at once — to a file, live to a running rerun viewer, and
recorded to MCAP for a later `falconry view` — and must show every entity family of every UAV at
more than one mission time. The same mission without a viewer must publish exactly the same
messages: the viewer never takes part in the tick protocol.
"""
from __future__ import annotations

import json
import signal
import subprocess
import warnings

import pytest

from services.lib.runtime.zenoh_config import free_port
from services.tools.viz.scene import UAV_FAMILIES, WORLD_FAMILIES
from tests.conftest import REPO, falconry_argv
from tests.tools.rrd import RERUN, entity_times, family_times, verify
from tests.tools.run import wait_for_port

PLOT_FAMILIES = ("plots/detections", "plots/cpu", "plots/lag_ms", "plots/nearest_partner", "plots/track_uncertainty",
                 "plots/map_age_ms")
# Short job manager timers, so that forbidden zones (seed 004 §3.5.2) appear within the run.
QUICK_ZONES = "[job_manager]\nchecking_timeout = 0.5\ngoing_timeout = 0.5\n"


# A yard where each UAV meets a drone right after take-off, so that the classifier detects it (and
# the tracker, the job manager's checks and forbidden zones follow) within a short run: the
# built-in scenarios find their targets later, and mbzirc's balloons on poles are background.
# The drones drift slowly: a moving target is chased rather than checked, and leaves no zone. Two
# more take off later, so new tracks start while the first ones are confirmed. A red balloon ahead
# of uav1 gives its camera something to find.
YARD = """
name = "viewer_yard"
duration = 20.0
uavs = 2
min_height = 1.0
max_height = 15.0
arena = [[0.0, 0.0], [60.0, 0.0], [60.0, 45.0], [0.0, 45.0]]
starts = [[20.0, 3.0, 1.5708], [40.0, 3.0, 1.5708]]

[uav]
sensor = "os0-64-512"

[[drones]]
name = "left"
center = [20.0, 15.0, 6.0]
radius = 2.0
speed = 0.3

[[drones]]
name = "right"
center = [40.0, 15.0, 6.0]
radius = 2.0
speed = -0.3

[[drones]]
name = "late_left"
center = [12.0, 12.0, 4.0]
radius = 1.0
speed = 0.3
takeoff_time = 4.0
climb_speed = 2.0

[[drones]]
name = "late_right"
center = [48.0, 12.0, 4.0]
radius = 1.0
speed = 0.3
takeoff_time = 4.0
climb_speed = 2.0

[[balloons]]
name = "ahead"
pole = [24.0, 24.0]
height = 3.0

[[obstacles]]
name = "hangar"
kind = "box"
center = [30.0, 35.0, 4.0]
size = [12.0, 8.0, 8.0]
"""


def mission(tmp_path) -> tuple[str, ...]:
    config, scenario = tmp_path / "quick_zones.toml", tmp_path / "viewer_yard.toml"
    config.write_text(QUICK_ZONES)
    scenario.write_text(YARD)
    return ("sim", str(scenario), "--uavs", "2", "--lockstep", "--duration", "20", "--seed", "1", "--quiet",
            "--progress", "0", "--config", str(config))


def missing_families(path, uavs=("uav1", "uav2"), at_least: int = 2) -> list[str]:
    """Families without something drawn (a point, a box, a text ...) at `at_least` distinct mission
    times; static world entities need any data."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # a live capture has no footer; the reader says so
        drawn = entity_times(path, with_content=True)
    missing = []
    for family in [f"{u}/{f}" for u in uavs for f in UAV_FAMILIES] + list(WORLD_FAMILIES) + list(PLOT_FAMILIES):
        times = family_times(drawn, family)
        static = family.startswith("world/")
        if (static and not times) or (not static and len(times - {-1}) < at_least):
            missing.append(f"{family} ({len(times)} times)")
    return missing


@pytest.fixture
def live_viewer(tmp_path):
    """A real rerun viewer process that saves what it receives (no window needed)."""
    port = free_port()
    saved = tmp_path / "live.rrd"
    proc = subprocess.Popen([RERUN, "--port", str(port), "--bind", "127.0.0.1", "--save", str(saved)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    wait_for_port(port)
    yield f"rerun+http://127.0.0.1:{port}/proxy", saved, proc
    if proc.poll() is None:
        proc.kill()
        proc.wait()


@pytest.mark.heavy  # a 20 s mission drawn three ways, ~60 s: make acceptance (make test's 15 minutes;
# the scene, the file output and the live viewer each have light tests: test_viz_scene/_output/_live)
def test_a_lockstep_mission_is_drawn_to_a_file_live_and_from_its_recording(tmp_path, port, live_viewer):
    address, live_rrd, viewer_process = live_viewer
    rrd, mcap, png = tmp_path / "run.rrd", tmp_path / "run.mcap", tmp_path / "run.png"
    drawn = subprocess.run(
        falconry_argv(*mission(tmp_path), "--port", str(port), "--rrd", str(rrd), "--viz", address, "--record", str(mcap),
                      "--plot", str(png), "--digest-json", str(tmp_path / "with_viewer.json")),
        cwd=REPO, capture_output=True, text=True, timeout=400)
    assert drawn.returncode == 0, drawn.stdout[-3000:] + drawn.stderr[-3000:]
    assert "rerun recording: " in drawn.stdout and "timeline plot: " in drawn.stdout
    print(drawn.stdout.splitlines()[-2])

    checked = verify(rrd)
    assert checked.returncode == 0, checked.stderr[-2000:]
    assert missing_families(rrd) == []
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 20_000

    viewer_process.send_signal(signal.SIGINT)
    viewer_process.wait(timeout=30)
    assert missing_families(live_rrd) == [], "the live viewer did not get every family"

    converted = tmp_path / "converted.rrd"
    view = subprocess.run(falconry_argv("view", str(mcap), "--rrd", str(converted), "--quiet"),
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert view.returncode == 0, view.stdout[-2000:] + view.stderr[-2000:]
    print(view.stdout.strip())
    assert verify(converted).returncode == 0
    assert missing_families(converted) == []

    # The same seeded mission without any viewer publishes exactly the same messages.
    plain = subprocess.run(falconry_argv(*mission(tmp_path), "--port", str(free_port()), "--digest-json",
                                         str(tmp_path / "without_viewer.json")),
                           cwd=REPO, capture_output=True, text=True, timeout=400)
    assert plain.returncode == 0, plain.stdout[-2000:]
    with_viewer = json.loads((tmp_path / "with_viewer.json").read_text())
    without = json.loads((tmp_path / "without_viewer.json").read_text())
    assert with_viewer.keys() == without.keys()
    assert [k for k in with_viewer if with_viewer[k] != without[k]] == []
