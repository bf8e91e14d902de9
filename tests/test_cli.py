"""The command line explains itself and turns user mistakes into one-line errors (exit 2)."""
from __future__ import annotations

import os
import subprocess

import pytest

from tests.conftest import REPO, falconry_argv


def falconry(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run(falconry_argv(*args), cwd=REPO, capture_output=True, text=True, timeout=timeout)


@pytest.mark.parametrize("command", [(), ("sim",), ("run",), ("health",), ("view",), ("record",), ("analyze", "hit-probability"),
                                     ("export",), ("completion",)])
def test_help_explains_every_option(command):
    result = falconry(*command, "--help")
    assert result.returncode == 0
    lines = result.stdout.splitlines()
    options = [line.split()[0] for line in lines if line.strip().startswith("--")]
    assert options, result.stdout
    for line in lines:  # every option line carries an explanation (on it or on the next line)
        if line.strip().startswith("--") and len(line.split()) < 3:
            following = lines[lines.index(line) + 1]
            assert following.startswith(" " * 10) and following.strip(), f"undocumented option: {line}"


@pytest.mark.parametrize("args, expected", [
    (("sim", "no_such_scenario"), "unknown scenario"),
    (("sim", "/tmp/definitely/missing.toml"), "missing.toml"),
    (("sim", "--uavs", "7"), "invalid choice"),
    (("sim", "--duration", "-3"), "--duration must be positive"),
    (("sim", "--bogus-option"), "unrecognized arguments"),
    (("run", "tracker"), "give --uav"),
    (("run", "simulator", "--uav", "uav1"), "takes no --uav"),
    (("run", "tracker", "--uav", "UAV 1"), "invalid UAV name"),
    (("run", "warp_drive", "--uav", "uav1"), "invalid choice"),
    (("run", "tracker", "--uav", "uav1", "--config", "/nonexistent.toml"), "config file not found"),
    (("run", "tracker", "--uav", "uav1", "--zenoh-config", "/nonexistent.json5"), "zenoh config file not found"),
    (("health",), "--connect"),
    (("view",), "give a recording"),
    (("view", "/tmp/definitely/missing.mcap"), "no such recording"),
    (("view", str(REPO / "README.md"), "--rrd", "/tmp/never-written.rrd"), "is not an MCAP file"),
    (("view", "--connect", "tcp/127.0.0.1:9", "--viz", "bogus"), "--viz takes spawn, web or"),
    (("view", "--connect", "tcp/127.0.0.1:9", "--viz", "rerun+http://127.0.0.1:9/proxy"), "no rerun viewer answers"),
    (("view", "--connect", "tcp/127.0.0.1:9", "--rrd", "/tmp"), "is a directory"),
    (("view", "--connect", "tcp/127.0.0.1:9", "--rrd", "/tmp/x.rrd", "--scan-hz", "0"), "--scan-hz must be positive"),
    (("view", "--connect", "tcp/127.0.0.1:9", "--rrd", "/definitely/missing/dir/x.rrd"), "--rrd: no such directory"),
    (("sim", "--viz", "bogus"), "--viz takes spawn, web or"),
    (("sim", "--plot", "/tmp/timeline.txt"), "--plot writes a PNG"),
    (("sim", "--rrd", "/definitely/missing/dir/run.rrd"), "--rrd: no such directory"),
    (("record", "/tmp/x.mcap", "--connect", "tcp/127.0.0.1:9", "--health", "-1"), "--health must be"),
    (("analyze",), "required: ANALYSIS"),
    (("analyze", "hit-probability", "--noise", "rtk=0.02,0.1"), "give NAME=POSITION_M,ATTITUDE_DEG,RANGE_M"),
    (("analyze", "hit-probability", "--noise", "bad=-1,0,0"), "must be finite and not negative"),
    (("analyze", "hit-probability", "--step", "0"), "must be positive"),
    (("analyze", "hit-probability", "--plot", "/tmp/p.txt"), "--plot writes a PNG"),
    (("colors", "pick", "/tmp/definitely/missing.png", "--roi", "1,1,2,2"), "no such file"),
    (("colors", "pick", str(REPO / "README.md"), "--roi", "1,1,2,2"), "not an image OpenCV can read"),
    (("colors", "pick", "/tmp/x.png", "--roi", "1,1,0,2"), "w and h > 0"),
    (("colors", "pick", "/tmp/x.png", "--roi", "1,1"), "give x,y,w,h"),
    (("colors", "show", "/tmp/x.png", "--colors", "no_such_colour", "--out", "/tmp/y.png"), "colour file not found"),
    (("snapshot", "--out", "/tmp/y.png"), "--connect"),
    (("frobnicate",), "invalid choice"),
])
@pytest.mark.slow(1.5)
def test_user_mistakes_give_one_line_and_exit_2(args, expected):
    result = falconry(*args)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    error_lines = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(error_lines) == 1 and expected in error_lines[0], result.stderr


def test_colour_picking_mistakes_give_one_line_and_exit_2(tmp_path):
    """An ROI outside the image, a colour file that is not one, Object Detect started without one."""
    import cv2
    import numpy as np
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), np.full((40, 60, 3), 90, np.uint8))
    bad = tmp_path / "bad.toml"
    bad.write_text("diameter = 0.6\n")
    config = tmp_path / "params.toml"
    config.write_text(f'[object_detect]\ncolors = "{tmp_path / "missing.toml"}"\n')
    for args, expected in [(("colors", "pick", str(image), "--roi", "50,30,20,5"), "reaches outside the 60 × 40 image"),
                           (("colors", "show", str(image), "--colors", str(bad), "--out", str(tmp_path / "s.png")),
                            "missing field 'thresholds'"),
                           (("colors", "pick", str(image), "--roi", "1,1,2,2", "--append", str(bad)),
                            "not a colour file written by"),
                           (("run", "object_detect", "--uav", "uav1", "--config", str(config)),
                            "colour file not found"),
                           (("run", "tracker", "--uav", "uav1", "--simulated-faults", "off"),
                            "--simulated-faults off needs --clock wall")]:
        result = falconry(*args)
        assert result.returncode == 2, result.stderr
        assert "Traceback" not in result.stderr
        error_lines = [line for line in result.stderr.splitlines() if "error" in line.lower()]
        assert len(error_lines) == 1 and expected in error_lines[0], result.stderr


def test_bad_parameter_file_names_table_and_field(tmp_path):
    config = tmp_path / "params.toml"
    config.write_text("[tracker]\nno_such_param = 3\n")
    result = falconry("run", "tracker", "--uav", "uav1", "--config", str(config))
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "no_such_param" in result.stderr and "tracker" in result.stderr
    config.write_text("[warp]\nx = 1\n")
    result = falconry("sim", "--config", str(config))
    assert result.returncode == 2 and "unknown table [warp]" in result.stderr
    for timeout in ("inf", "1e-12", "-1.0"):  # a flight controller that never, or always, calls its estimate old
        config.write_text(f"[simulator]\nestimate_timeout = {timeout}\n")
        result = falconry("run", "simulator", "--config", str(config))
        assert result.returncode == 2 and "Traceback" not in result.stderr
        assert "estimate_timeout must be a positive number of seconds" in result.stderr, result.stderr


def test_a_native_viewer_without_a_display_says_what_to_use_instead():
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    for args in (("sim", "--viz"), ("view", "--connect", "tcp/127.0.0.1:9")):
        result = subprocess.run(falconry_argv(*args), cwd=REPO, capture_output=True, text=True, timeout=60, env=env)
        assert result.returncode == 2 and "Traceback" not in result.stderr
        assert "no display for a native viewer" in result.stderr and "--viz web" in result.stderr, result.stderr


def test_the_summary_sums_each_services_cpu_over_the_uavs_largest_first():
    from services.tools.launcher.sim_cmd import cpu_line

    cpu = {"uav1/mapper": 2.0, "uav2/mapper": 3.0, "uav1/classifier": 1.0, "sim/simulator": 0.5, "launcher": 0.7}
    assert cpu_line(cpu) == "mapper 5.0, classifier 1.0, launcher 0.7, simulator 0.5"


def test_messages_missed_by_a_stopped_service_are_counted_apart_from_the_deliverys_losses():
    """A killed or frozen service misses what is sent while it is gone, by an amount that follows
    wall time; the delivery's own losses are what services that ran throughout did not receive."""
    from schemas.messages import FaultCommand, Header, ServiceHealth
    from services.tools.launcher.sim_cmd import health_totals, stopped_services

    def health(uav, service, received=None, published=None):
        return ServiceHealth(header=Header(), uav=uav, service=service, pid=1, uptime=1.0, state="running",
                             received=received or {}, published=published or {})

    odometry, status = "falconry/uav1/odometry", "falconry/uav1/status"
    usage = [health("sim", "simulator", published={odometry: 100}),
             health("uav1", "job_manager", received={odometry: 97}, published={status: 50}),
             health("uav1", "planner", received={odometry: 40, status: 20}),  # killed and restarted
             health("uav2", "planner", received={odometry: 10})]  # another UAV's key: not its own
    faults = [FaultCommand(header=Header(), kind="kill", uav="uav1", service="planner")]
    totals = health_totals(usage, stopped_services(faults, restarted=set()))
    assert (totals["lost_own_uav"], totals["missed_while_stopped"]) == (3, 60 + 30)
    assert stopped_services([], restarted={"uav1/planner"}) == {"uav1/planner"}
    whole_uav = stopped_services([FaultCommand(header=Header(), kind="freeze", uav="uav1")], set())
    assert health_totals(usage, whole_uav)["lost_own_uav"] == 0


def test_health_is_asked_again_until_a_message_still_on_its_way_has_arrived():
    """The planner's reference of the last tick reaches the job manager after the question did once
    in a while: asked again, it is received; a message the network lost stays lost."""
    from schemas.messages import Header, ServiceHealth
    from services.tools.launcher.sim_cmd import health_totals, until_received

    reference = "falconry/uav1/reference"

    def answers(received, *, job_manager=True):
        planner = ServiceHealth(header=Header(), uav="uav1", service="planner", pid=1, uptime=1.0,
                                state="running", published={reference: 900})
        manager = ServiceHealth(header=Header(), uav="uav1", service="job_manager", pid=2, uptime=1.0,
                                state="running", received={reference: received})
        return [planner, manager] if job_manager else [planner]

    def lost(usage):
        return health_totals(usage)["lost_own_uav"]

    later = iter([answers(0, job_manager=False), answers(900)])  # an answer lost on the way, then the full one
    settled = until_received(answers(899), lambda: next(later), lost, pause_s=0.0)
    assert lost(settled) == 0
    asked = []
    gone = until_received(answers(899), lambda: asked.append(1) or answers(899), lost, attempts=3, pause_s=0.0)
    assert (lost(gone), len(asked)) == (1, 3)
    assert until_received(answers(900), lambda: asked.append(1) or answers(0), lost, pause_s=0.0) is not None
    assert len(asked) == 3  # nothing missing: not asked again


def test_only_the_masters_own_give_ups_make_a_lockstep_run_another_than_its_seeds():
    """A frozen service's downstream gives up on it by design; the simulator going on without a
    live service is what changes the run."""
    from schemas.messages import Header, ServiceHealth
    from services.tools.launcher.sim_cmd import health_totals

    def health(uav, service, timeouts):
        return ServiceHealth(header=Header(), uav=uav, service=service, pid=1, uptime=1.0, state="running",
                             lockstep_timeouts=timeouts)

    frozen_downstream = [health("sim", "simulator", 0), health("uav1", "job_manager", 12)]
    assert health_totals(frozen_downstream)["ticks_gone_on_without"] == 0
    assert health_totals(frozen_downstream)["lockstep_timeouts"] == 12
    went_on = [health("sim", "simulator", 2), health("uav1", "job_manager", 2)]
    assert health_totals(went_on)["ticks_gone_on_without"] == 2


def test_the_launchers_light_service_entry_is_falconry_run():
    """The launcher starts services with `python -m services.tools.launcher.run_service`: the same `run`
    command (its options, its one-line errors) without importing every other command."""
    import subprocess
    import sys

    def entry(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "-m", "services.tools.launcher.run_service", *args],
                              capture_output=True, text=True, timeout=60)
    full, light = falconry("run", "--help"), entry("run", "--help")
    assert light.returncode == 0 and light.stdout == full.stdout
    for args in (("run", "tracker"), ("run", "tracker", "--uav", "uav1", "--log-level", "loud")):
        a, b = falconry(*args), entry(*args)
        assert (a.returncode, a.stderr) == (b.returncode, b.stderr) and b.returncode == 2, b.stderr
    imported = subprocess.run([sys.executable, "-c", "import sys, services.tools.launcher.run_service; "
                               "print(sorted(m for m in sys.modules if m.endswith('_cmd')))"],
                              capture_output=True, text=True, timeout=60)
    assert imported.stdout.strip() == "['services.tools.launcher.run_cmd']", imported.stdout
