"""The fault campaign: seeded schedules that are valid scenario faults, and a small campaign end to end."""
from __future__ import annotations

import subprocess
import tomllib

import pytest

from services.simulator.scenario import SCENARIO_DIR, parse_scenario
from services.tools.launcher import netns
from services.tools.launcher.campaign import (
    EARLIEST,
    HEADER,
    LATEST_BEFORE_END,
    RunPlan,
    RunResult,
    draw_runs,
    row,
    totals,
)
from tests.conftest import falconry_argv


def test_a_campaign_is_the_same_list_of_valid_runs_for_the_same_seed():
    runs = draw_runs(40, seed=7, duration=90.0)
    assert runs == draw_runs(40, seed=7, duration=90.0) and runs != draw_runs(40, seed=8, duration=90.0)
    assert [r.uavs for r in runs[:4]] == [2, 3, 2, 3]
    drawn = set()
    for run in runs:
        base = tomllib.loads((SCENARIO_DIR / "mbzirc.toml").read_text())
        faults = tomllib.loads("\n".join(f.toml() for f in run.faults))["faults"]
        scenario = parse_scenario({**base, "uavs": run.uavs, "faults": faults}, "campaign.toml")  # validates
        for fault in scenario.faults:
            assert EARLIEST <= fault.time <= 90.0 - LATEST_BEFORE_END
            assert int(fault.uav.removeprefix("uav")) <= run.uavs
        drawn |= {f.kind + ("_" + f.failsafe if f.kind == "kill" and not f.service else "") for f in run.faults}
    assert {"link_cut", "kill_hold", "kill_land", "freeze", "odometry_jump"} <= drawn
    assert all(f.kind == "link_cut" for r in draw_runs(10, 1, 90.0, kinds=("link_cut",)) for f in r.faults)
    with pytest.raises(ValueError):
        draw_runs(1, 1, 20.0)  # no room for a fault between take-off and the end


def summary(collisions: int = 0, clearances=(1.84, 0.93), violations: int = 0) -> dict:
    """What a run's --summary-json says, the parts the table reads."""
    return {"outcome": "finished", "min_separation": {"m": 6.2, "t": 40.0, "pair": "uav1-uav2"},
            "separation_violations": [{"start": 1.0, "end": 2.0, "pair": "uav1-uav2", "m": 4.0}] * violations,
            "collisions": [{"t": 55.9, "uav": "uav1", "with": "tree2", "detail": "tree2 at 4.1 m/s (10.3, 29.1, 5.0)"}]
            * collisions,
            "clearance": {f"uav{k + 1}": {"m": m, "to": "tree2", "t": 50.0, "attack_pole": None}
                          for k, m in enumerate(clearances)},
            "destroyed": [], "targets": 5, "uavs": {}, "restarts": [],
            "health": {"handler_errors": 0, "decode_errors": 0, "lost_own_uav": 0}}


def test_a_collision_fails_a_run_like_a_separation_violation_and_the_table_shows_clearance():
    plan = RunPlan(1, 42, 2)
    clean = RunResult.from_summary(plan, summary())
    crashed = RunResult.from_summary(plan, summary(collisions=1, clearances=(0.61, None)))
    too_close = RunResult.from_summary(plan, summary(violations=1))
    never_flew = RunResult.from_summary(plan, summary(clearances=(None, None)))
    assert (clean.collisions, clean.clearance, clean.ok) == (0, 0.93, True)
    assert (crashed.collisions, crashed.clearance, crashed.ok) == (1, 0.61, False)
    assert not too_close.ok and never_flew.clearance is None and never_flew.ok
    assert RunResult.from_summary(plan, {}).clearance is None  # a run that wrote no summary
    short = RunResult.from_summary(plan, {**summary(), "started_without": ["uav2/job_manager"]})
    assert (short.outcome, short.ok) == ("started short", False)  # another mission than its seed's
    columns = HEADER.split()
    assert columns[columns.index("viol") + 1:columns.index("viol") + 4] == ["coll", "clear", "m"]
    cells = row(crashed).split()
    assert cells[cells.index("6.2") + 1:cells.index("6.2") + 4] == ["0", "1", "0.61"]  # viol, coll, clear m
    assert row(never_flew).split()[cells.index("6.2") + 3] == "-"
    assert len(row(clean)) == len(row(crashed))  # the columns line up
    lines = totals([clean, crashed, never_flew], 5.0)
    assert "collisions: 1; smallest clearance to an obstacle over all runs: 0.61 m" in lines[1]


def test_an_engagement_at_no_target_or_a_geofence_breach_fails_a_run_and_runs_take_the_scenarios_in_turn():
    runs = draw_runs(6, seed=7, duration=90.0, scenarios=("mbzirc", "intruder", "agile"))
    assert [(r.scenario, r.uavs) for r in runs] == [("mbzirc", 2), ("intruder", 3), ("agile", 2), ("mbzirc", 3),
                                                   ("intruder", 2), ("agile", 3)]
    assert [(r.seed, r.faults) for r in runs] == [(r.seed, r.faults) for r in draw_runs(6, seed=7, duration=90.0)]
    aimed = {"uavs": {"uav1": {"engagements": [{"t": 20.0, "action": "attack", "aim": [1.0, 2.0, 3.0],
                                                 "target": "balloon1", "miss_m": 0.1},
                                                {"t": 30.0, "action": "intercept", "aim": [9.0, 2.0, 21.0],
                                                 "target": None, "miss_m": 31.0}]}}}
    wrong = RunResult.from_summary(runs[1], {**summary(), **aimed})
    out = RunResult.from_summary(runs[1], {**summary(), "geofence_breaches": [{"uav": "uav1", "start": 3.0,
                                                                            "end": 4.0, "m": 1.5}]})
    assert (wrong.no_target, wrong.ok) == (1, False) and (out.geofence, out.ok) == (1, False)
    cells, columns = row(wrong).split(), HEADER.split()
    assert cells[3] == "intruder" and columns[3] == "scenario"
    assert columns[columns.index("no-tgt") + 1] == "fence"
    assert "engagements at no target: 1; geofence breaches (out of the arena or above its ceiling): 1" in \
        totals([wrong, out], 5.0)[2]


def test_the_campaigns_arena_picture_marks_where_each_engagement_aimed(tmp_path):
    from services.simulator.scenario import load_scenario
    from services.tools.launcher.plot import plot_arena

    aimed = {"uavs": {"uav1": {"engagements": [{"t": 30.0, "action": "intercept", "aim": [9.0, 2.0, 21.0],
                                                 "target": None, "miss_m": 31.0}]}}}
    picture = tmp_path / "mbzirc.png"
    plot_arena(load_scenario("mbzirc"), [aimed, {}], picture, "mbzirc")
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and picture.stat().st_size > 10_000


@pytest.mark.timeout(600)
@pytest.mark.skipif(netns.available() is not None, reason=f"link_cut needs {netns.available()}")
@pytest.mark.slow(150)
def test_a_small_campaign_keeps_the_team_apart_and_prints_its_table(tmp_path):
    # 36 s, the shortest run a campaign draws a fault for: uav2 killed (hold) at 10.8 s of a 2-UAV run,
    # uav3's link cut at 10.5 s for 16.9 s of a 3-UAV run
    result = subprocess.run(falconry_argv("campaign", "--runs", "2", "--seed", "5", "--duration", "36",
                                          "--kinds", "link_cut,kill_hold", "--out", str(tmp_path)),
                            capture_output=True, text=True, timeout=500)
    print(result.stdout[-2500:])
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-2000:]
    assert "runs finished: 2/2; separation violations (closer than 5 m): 0" in result.stdout
    assert "collisions: 0; smallest clearance to an obstacle over all runs: " in result.stdout
    assert "handler errors: 0;" in result.stdout
    table = result.stdout.split("run UAVs")[1].splitlines()
    assert len([line for line in table if line.strip().startswith(("1 ", "2 "))]) == 2
    assert sorted(p.name for p in tmp_path.glob("run*.json")) == ["run001.json", "run002.json"]
    services_log = (tmp_path / "run002.services.log").read_text()  # what each run's services said
    assert "uav1/job_manager" in services_log and "PREFLIGHT -> TAKING_OFF" in services_log
