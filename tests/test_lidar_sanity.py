"""The LiDAR sanity checks (services/lib/lidar/sanity.py) on scans the simulated sensor casts in a built-in
arena: a flight's scans pass, a garbage scan and a NaN burst fail, and detections made while the
sensor fails or settles are not trusted by the tracker or the job manager."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.messages import Obstacle
from services.job_manager.core import JobManager, State
from services.job_manager.params import JobManagerParams
from services.lib.lidar.models import lidar_model
from services.lib.lidar.sanity import NS, SanityLimits, ScanSanity, SensorTrust, scan_figures
from services.lib.world.primitives import primitives_from_obstacles
from services.sensor_driver.core import scan
from services.sensor_driver.faults import faulty_scan
from services.simulator.scenario import load_scenario
from services.tracker.core import TrackerCore, TrackerParams

PERIOD = NS // 10


def arena_world(name: str):
    scenario = load_scenario(name)
    return primitives_from_obstacles([*scenario.obstacles, Obstacle(kind="plane", center=(0.0, 0.0, scenario.ground_z))])


def flight(name: str, model_name: str, frames: int, seed: int = 0):
    """(stamp, points, origin, beams, model) of a take-off, then a turning sweep, from the arena's first start."""
    world, model = arena_world(name), lidar_model(model_name)
    start = np.asarray(load_scenario(name).starts[0][:2], dtype=float)
    rng = np.random.default_rng(seed)
    for f in range(frames):
        origin = np.array([*(start + 0.5 * max(f - 20, 0) * np.array([1.0, 0.3])), min(0.5 + 0.3 * f, 6.0)])
        heading = 0.06 * f
        beams = model.directions(f)
        yield f * PERIOD, scan(origin, heading, beams, world, rng, min_range=model.min_range,
                               max_range=model.max_range), origin, beams, model


def figures(result, origin, model):
    return scan_figures(result.points, origin, model.min_range, model.max_range)


@pytest.mark.parametrize("arena, model", [("forest", "os1-64"), ("mbzirc", "mid360"), ("street", "os0-32")])
def test_the_scans_of_a_take_off_and_a_turning_sweep_all_pass(arena, model):
    sanity = ScanSanity()
    failed = [(stamp, reason) for stamp, result, origin, _, m in flight(arena, model, 60)
              if (reason := sanity.check(stamp, figures(result, origin, m)))]
    assert failed == []


@pytest.mark.parametrize("kind, check", [("lidar_garbage", "no sky"), ("lidar_nan", "no return")])
def test_a_burst_of_garbage_or_nan_fails_every_scan_and_the_sensor_recovers_after(kind, check):
    sanity, trust = ScanSanity(), SensorTrust(settle_time=1.0)
    verdicts = {}
    rng = np.random.default_rng(1)
    for stamp, result, origin, beams, m in flight("forest", "os1-64", 50):
        if 30 <= stamp // PERIOD < 35:  # a 0.5 s burst
            result = faulty_scan(result, kind, origin, beams, m.min_range, m.max_range, rng)
        reason = sanity.check(stamp, figures(result, origin, m))
        trust.note(stamp, not reason)
        verdicts[stamp // PERIOD] = (bool(reason), trust.trusted(stamp))
    assert [f for f, (failed, _) in verdicts.items() if failed] == [30, 31, 32, 33, 34]
    assert sanity.failures == {check: 5}
    assert [f for f, (_, trusted) in verdicts.items() if not trusted] == list(range(30, 45))  # + 1 s settling


def test_returns_on_every_beam_within_range_fail_and_a_scan_whose_count_jumps_fails():
    sanity = ScanSanity(SanityLimits(max_return_share=1.5))  # "no sky" off: the jump must still catch it
    stamps = iter(range(0, 100 * PERIOD, PERIOD))
    frames = list(flight("mbzirc", "os1-64", 12))
    for stamp, result, origin, _, m in frames[:10]:
        assert sanity.check(next(stamps), figures(result, origin, m)) == ""
    _, result, origin, beams, m = frames[10]
    garbage = faulty_scan(result, "lidar_garbage", origin, beams, m.min_range, m.max_range, np.random.default_rng(0))
    assert "return share jumped" in sanity.check(next(stamps), figures(garbage, origin, m))
    half = result.points.copy()
    half[:, : half.shape[1] * 4 // 5] = np.nan  # four fifths of the beams dead
    assert sanity.check(next(stamps), figures(type(result)(half, result.hits, None), origin, m)) != ""


def test_corrupted_coordinates_fail_and_a_long_fault_does_not_lock_the_sensor_out():
    sanity = ScanSanity()
    frames = list(flight("forest", "os1-64", 40))
    stamp, result, origin, _, m = frames[0]
    assert sanity.check(stamp, figures(result, origin, m)) == ""
    corrupt = result.points.copy()
    rows = np.flatnonzero(np.isfinite(corrupt.reshape(-1, 3)).all(axis=1))[::20]
    corrupt.reshape(-1, 3)[rows, 2] = np.inf  # one coordinate of every 20th return
    assert "not finite" in sanity.check(stamp + PERIOD, figures(type(result)(corrupt, result.hits, None), origin, m))
    # 3 s later the world looks different (climbed from 0.5 to 6 m); with no scan passing for
    # rebase_after, the next sound scan is the new reference
    stamp, result, origin, _, m = frames[35]
    assert sanity.check(30 * PERIOD + stamp, figures(result, origin, m)) == ""


def test_detections_made_while_the_sensor_fails_or_settles_start_no_track():
    core = TrackerCore(TrackerParams(confirm_detections=1, sensor_settle_time=1.0))
    junk = np.array([[10.0, 0.0, 5.0], [20.0, 5.0, 6.0]])
    assert core.new_detections(0, junk, sensor_health="no return on any beam") == [-1, -1]
    assert core.new_detections(NS // 2, junk) == [-1, -1]  # settling
    assert len(core) == 0 and core.counters.untrusted_detections == 4
    assert all(i >= 0 for i in core.new_detections(NS + NS // 10, junk))  # trusted again
    assert len(core) == 2


def test_the_job_manager_acts_on_no_detection_while_the_lidar_fails_or_settles_but_hears_its_heartbeat():
    jm = JobManager(JobManagerParams(sensor_settle_time=1.0), "uav1")
    jm.set_world(np.array([[0, 0], [100, 0], [100, 100], [0, 100]], dtype=float), ["uav1"], 600.0)
    jm.state = State.GOING_AROUND
    here = np.array([50.0, 50.0, 5.0])
    balloon = np.array([[55.0, 50.0, 5.0]])
    jm.observe_detections(0, balloon, sensor_health="returns on 100 % of beams (no sky)")
    assert jm.seen.scan_stamp == 0 and len(jm.candidates(0, here)) == 0
    jm.observe_detections(NS // 2, balloon)
    assert len(jm.candidates(NS // 2, here)) == 0  # settling
    jm.observe_detections(NS + NS // 5, balloon)
    assert len(jm.candidates(NS + NS // 5, here)) == 1


def numpy_figures(points, origin, min_range, max_range, blocked):
    """The checks' counts written plainly in numpy, what the compiled pass must give."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    open_beams = ~np.asarray(blocked, dtype=bool).reshape(-1)
    finite = np.isfinite(points)
    whole = finite.all(axis=1) & open_beams
    partial = finite.any(axis=1) & ~finite.all(axis=1) & open_beams
    ranges = np.linalg.norm(points[whole] - np.asarray(origin, dtype=np.float64), axis=1)
    slack = 1e-3 + 1e-4 * max_range
    outside = (ranges < min_range - slack) | (ranges > max_range + slack) if max_range > 0 else ranges < 0
    return int(open_beams.sum()), int(whole.sum() - outside.sum()), int(outside.sum() + partial.sum())


@settings(max_examples=200, deadline=None, derandomize=True, database=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 400), spread=st.floats(0.1, 200.0),
       dtype=st.sampled_from([np.float32, np.float64]), max_range=st.sampled_from([0.0, -1.0, 40.0, 90.0]))
def test_the_compiled_figures_are_the_plain_numpy_counts(seed, n, spread, dtype, max_range):
    rng = np.random.default_rng(seed)
    points = rng.normal(0.0, spread, (n, 3)).astype(dtype)
    odd = rng.random((n, 3))
    points[odd < 0.05], points[odd > 0.97] = np.nan, np.inf  # whole and partial corruption
    points[rng.random(n) < 0.02] *= -np.inf
    blocked = rng.random(n) < 0.1
    origin = rng.normal(0.0, 3.0, 3)
    got = scan_figures(points, origin, 0.3, max_range, blocked)
    assert (got.beams, got.returns, got.bad) == numpy_figures(points, origin, 0.3, max_range, blocked)
