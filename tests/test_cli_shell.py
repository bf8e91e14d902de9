"""What a person at a shell meets: `falconry --version`, completion scripts that a real bash
runs, --log-level before or after the command, `falconry health --service` as a health check
(exit status), and recordings that never replace each other."""
from __future__ import annotations

import datetime
import importlib.metadata
import subprocess
import time
from pathlib import Path

import pytest

from schemas import keys
from schemas.messages import Header, ServiceHealth
from services.lib.runtime.zenoh_config import free_port
from services.tools.launcher.cli import build_parser, main
from services.tools.launcher.health_cmd import ServiceName, parse_service_name, verdicts
from services.tools.launcher.record_cmd import recording_path
from tests.conftest import falconry_argv


def test_version_names_the_package_and_the_zenoh_it_speaks(capsys):
    with pytest.raises(SystemExit) as exit_:
        main(["--version"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out.strip()
    assert out.startswith(f"falconry {importlib.metadata.version('falconry')} ")
    assert f"eclipse-zenoh {importlib.metadata.version('eclipse-zenoh')}" in out


def test_log_level_is_taken_before_or_after_the_command_and_after_wins():
    parser = build_parser()
    assert parser.parse_args(["health", "--connect", "tcp/127.0.0.1:1"]).log_level == "info"
    assert parser.parse_args(["--log-level", "debug", "health"]).log_level == "debug"
    assert parser.parse_args(["health", "--log-level", "warning"]).log_level == "warning"
    assert parser.parse_args(["--log-level", "debug", "run", "tracker", "--log-level", "error"]).log_level == "error"


def test_a_bad_log_level_after_the_command_is_one_line_and_exit_2():
    out = subprocess.run(falconry_argv("record", "x.mcap", "--log-level", "loud"), capture_output=True, text=True)
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "invalid choice: 'loud'" in out.stderr


def bash_complete(script: str, words: list[str]) -> list[str]:
    """What a real bash offers for the last of `words` with the generated script loaded."""
    program = (f"source /dev/stdin <<'FALCONRY'\n{script}\nFALCONRY\n"
               f"COMP_WORDS=({' '.join(words)}); COMP_CWORD={len(words) - 1}; COMP_LINE='{' '.join(words)}'; "
               f"COMP_POINT=${{#COMP_LINE}}; _shtab_falconry; printf '%s\\n' \"${{COMPREPLY[@]}}\"")
    out = subprocess.run(["bash", "-c", program], capture_output=True, text=True, timeout=30)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_bash_completion_offers_commands_services_and_options():
    script = subprocess.run(falconry_argv("completion", "bash"), capture_output=True, text=True, check=True).stdout
    assert bash_complete(script, ["falconry", "he"]) == ["health"]
    assert bash_complete(script, ["falconry", "run", "track"]) == ["tracker"]
    assert "--detector" in bash_complete(script, ["falconry", "sim", "--det"])
    assert "--log-level" in bash_complete(script, ["falconry", "health", "--log"])
    commands = set(build_parser()._subparsers._group_actions[0].choices)
    assert set(bash_complete(script, ["falconry", "''"])) >= commands


@pytest.mark.parametrize("shell", ["zsh", "tcsh"])
def test_other_shells_get_a_script_naming_every_command(shell, capsys):
    assert main(["completion", shell]) == 0
    script = capsys.readouterr().out
    for command in ("sim", "run", "health", "record", "completion"):
        assert command in script


def test_an_unknown_shell_is_one_line_and_exit_2():
    out = subprocess.run(falconry_argv("completion", "fish"), capture_output=True, text=True)
    assert out.returncode == 2 and out.stderr.count("\n") == 1


def test_service_names_are_uav_slash_service_and_run_wide_ones_sim():
    assert parse_service_name("uav2/tracker") == ServiceName("uav2", "tracker")
    assert parse_service_name("simulator") == ServiceName(keys.SIM, "simulator")
    assert parse_service_name("sim/simulator") == ServiceName(keys.SIM, "simulator")
    for bad in ("uav1/trackr", "tracker", "uav1/simulator", "UAV1/tracker", "sim/tracker"):
        with pytest.raises(ValueError):
            parse_service_name(bad)


def _answer(uav: str, service: str, state: str) -> ServiceHealth:
    return ServiceHealth(header=Header(), uav=uav, service=service, pid=1,
                         uptime=1.0, state=state)


def test_healthy_means_every_named_service_answered_running():
    wanted = [ServiceName("uav1", "tracker"), ServiceName("uav1", "planner"), ServiceName("sim", "simulator")]
    answers = [_answer("uav1", "tracker", "running"), _answer("uav1", "planner", "starting"),
               _answer("uav2", "tracker", "running")]
    assert verdicts(wanted, answers) == {ServiceName("uav1", "planner"): "state starting",
                                        ServiceName("sim", "simulator"): "no answer"}
    assert verdicts(wanted[:1], answers) == {}


def test_health_service_exits_0_for_a_running_service_and_1_for_an_absent_one(hub, processes):
    _, endpoint = hub
    processes.start("run", "planner", "--uav", "uav1", "--connect", endpoint, "--exit-with-parent")

    def check(*names: str) -> subprocess.CompletedProcess:
        args = [a for name in names for a in ("--service", name)]
        return subprocess.run(falconry_argv("health", *args, "--connect", endpoint, "--timeout", "1"),
                              capture_output=True, text=True, timeout=30)

    deadline = time.monotonic() + 30
    while (out := check("uav1/planner")).returncode != 0 and time.monotonic() < deadline:
        time.sleep(0.5)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "uav1/planner" in out.stdout and "running" in out.stdout
    out = check("uav1/planner", "uav2/planner")
    assert out.returncode == 1
    assert "uav2/planner           unhealthy: no answer" in out.stdout


def test_a_recording_name_takes_the_utc_start_time():
    start = datetime.datetime(2026, 11, 25, 7, 15, 2, tzinfo=datetime.timezone(datetime.timedelta(hours=2)))
    assert recording_path("runs/flight-{start}.mcap", start) == "runs/flight-20261125T051502Z.mcap"
    assert recording_path("plain.mcap", start) == "plain.mcap"


def test_log_level_is_taken_after_nested_commands_too():
    parser = build_parser()
    args = parser.parse_args(["colors", "pick", "x.png", "--roi", "1,1,2,2", "--log-level", "debug"])
    assert args.log_level == "debug"
    assert parser.parse_args(["analyze", "hit-probability", "--log-level", "error"]).log_level == "error"


def test_a_health_check_says_unhealthy_when_the_router_is_out_of_reach():
    endpoint = f"tcp/127.0.0.1:{free_port()}"  # nothing listens there
    out = subprocess.run(falconry_argv("health", "--service", "uav1/planner", "--zenoh-profile", "router",
                                       "--connect", endpoint), capture_output=True, text=True, timeout=60)
    assert out.returncode == 1 and out.stdout.startswith("unhealthy: cannot open zenoh session"), out
    out = subprocess.run(falconry_argv("health", "--zenoh-profile", "router", "--connect", endpoint),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 75, "without --service it is a runtime failure, as for every command"


def test_a_non_positive_health_timeout_is_one_line_and_exit_2():
    out = subprocess.run(falconry_argv("health", "--timeout", "-1", "--connect", "tcp/127.0.0.1:1"),
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and out.stderr.count("\n") == 1 and "--timeout must be positive" in out.stderr


def test_a_start_named_recording_never_replaces_one_made_in_the_same_second(tmp_path):
    start = datetime.datetime(2026, 11, 25, 5, 15, 2, tzinfo=datetime.timezone.utc)
    template = str(tmp_path / "flight-{start}.mcap")
    first = recording_path(template, start)
    Path(first).write_bytes(b"a recording")
    second = recording_path(template, start)
    assert second == str(tmp_path / "flight-20261125T051502Z-2.mcap")
    Path(second).touch()
    assert recording_path(template, start).endswith("-3.mcap")
    plain = tmp_path / "plain.mcap"
    plain.touch()
    assert recording_path(str(plain), start) == str(plain), "a fixed name is replaced, as documented"
