"""The onboard systemd units: generated from the service list, checked in as generated, parsed
by systemd itself (`systemd-analyze verify`, which only warns about a bad line, so any word from
it fails the test), and each ExecStart accepted by the real `falconry` parser."""
from __future__ import annotations

import configparser
import os
import contextlib
import io
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from schemas import keys
from services.tools.launcher.cli import build_parser, main
from services.tools.launcher.systemd_units import (ROUTER_UNIT, TARGET_UNIT, UnitSettings, render_units, unit_name)
from services.lib.runtime.errors import USAGE_ERROR
from services.lib.runtime.zenoh_config import free_port
from tests.conftest import REPO

CHECKED_IN = REPO / "deploy" / "onboard" / "systemd"
VENV = str(Path(sys.executable).parent.parent)


def parse_unit(text: str) -> configparser.ConfigParser:
    parser = configparser.ConfigParser(strict=False, interpolation=None, delimiters=("=",))
    parser.optionxform = str  # systemd keys are case-sensitive
    parser.read_string(text.replace("\\\n", " "))
    return parser


def exec_start_args(unit: configparser.ConfigParser, uav: str) -> list[str]:
    words = shlex.split(unit["Service"]["ExecStart"].replace("%i", uav))
    return [w.replace("${FALCONRY_ZENOH}", "tcp/127.0.0.1:7447") for w in words]


def test_the_checked_in_units_are_the_generators_output():
    generated = render_units(UnitSettings())
    assert {p.name for p in CHECKED_IN.iterdir()} == set(generated), "run `falconry units deploy/onboard/systemd`"
    for name, text in generated.items():
        assert (CHECKED_IN / name).read_text() == text, f"{name} differs: run `falconry units deploy/onboard/systemd`"


@pytest.mark.parametrize("positioning", keys.POSITIONING)
@pytest.mark.parametrize("detector", keys.DETECTORS)
def test_one_unit_per_service_the_simulator_expects_and_a_target_wanting_them_all(detector, positioning):
    units = render_units(UnitSettings(detector=detector, positioning=positioning))
    services = keys.uav_services(detector, positioning)
    assert (keys.LOCALIZER in services) == (positioning == "lidar")
    assert set(units) == {unit_name(s) for s in services} | {ROUTER_UNIT, TARGET_UNIT}
    wants = parse_unit(units[TARGET_UNIT])["Unit"]["Wants"].split()
    assert sorted(wants) == sorted(n.replace("@.", "@%i.") for n in units if n != TARGET_UNIT)


def test_every_exec_start_is_a_falconry_command_on_wall_time_after_the_router():
    for name, text in render_units(UnitSettings(positioning="lidar")).items():  # every unit, the localizer's too
        if name == TARGET_UNIT:
            continue
        unit = parse_unit(text)
        args = exec_start_args(unit, "uav2")
        assert args[0] == UnitSettings().falconry, name
        with contextlib.redirect_stderr(io.StringIO()):
            parsed = build_parser().parse_args(args[1:])
        service = unit["Service"]
        assert service["RestartPreventExitStatus"] == str(USAGE_ERROR), name
        assert unit["Unit"]["StartLimitIntervalSec"] == "0", name
        assert service["User"] == "falconry" and service["NoNewPrivileges"] == "yes", name
        if name == ROUTER_UNIT:
            assert parsed.command == "router"
            continue
        assert (parsed.command, parsed.uav, parsed.clock, parsed.zenoh_profile) == ("run", "uav2", "wall", "router")
        assert name == unit_name(parsed.service)
        assert "falconry-router@%i.service" in unit["Unit"]["After"].split()
        assert "time-sync.target" in unit["Unit"]["After"].split()
        assert service["Restart"] == "on-failure"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_systemd_accepts_every_unit(tmp_path):
    """Rendered for this venv, so each ExecStart names an executable that exists; without GNSS, so
    the localizer's unit is checked too."""
    assert main(["units", str(tmp_path), "--prefix", VENV, "--positioning", "lidar"]) == 0
    assert (tmp_path / unit_name(keys.LOCALIZER)).is_file()
    instances = []
    for unit in tmp_path.iterdir():
        instance = tmp_path / unit.name.replace("@.", "@uav1.")
        instance.symlink_to(unit.name)
        instances.append(str(instance))
    out = subprocess.run(["systemd-analyze", "verify", "--man=no", *instances], capture_output=True, text=True,
                         timeout=60, env={"SYSTEMD_LOG_LEVEL": "warning", "PATH": "/usr/bin:/bin"})
    complaints = [line for line in (out.stdout + out.stderr).splitlines() if line.strip()]
    assert out.returncode == 0 and not complaints, "\n".join(complaints)


def test_a_broken_unit_is_caught_by_the_systemd_check(tmp_path):
    """The check above can fail: systemd says so when a value does not parse."""
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed here")
    main(["units", str(tmp_path), "--prefix", VENV])
    broken = tmp_path / unit_name("planner")
    broken.write_text(broken.read_text().replace("Type=exec", "Type=exek"))
    (tmp_path / "falconry-planner@uav1.service").symlink_to(broken.name)
    out = subprocess.run(["systemd-analyze", "verify", "--man=no", str(tmp_path / "falconry-planner@uav1.service")],
                         capture_output=True, text=True, timeout=60)
    assert "exek" in out.stderr


def test_units_refuses_a_relative_prefix_in_one_line(tmp_path, capsys):
    assert main(["units", str(tmp_path), "--prefix", "venv"]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_the_router_unit_runs_the_shipped_onboard_file_with_its_access_control(tmp_path, processes):
    """What falconry-router@uav1 runs, `falconry router --zenoh-config FILE`, on the shipped
    deploy/onboard/uav1/router.json5 with only the certificate directory moved and the endpoints
    put on this test's ports: uav2's client is admitted for its own status, never for uav1's command."""
    from tests.test_tls import Inbox, command, member, publish_until, status
    assert main(["certs", str(tmp_path / "tls"), "--uavs", "3", "--days", "1"]) == 0
    shipped = (REPO / "deploy" / "onboard" / "uav1" / "router.json5").read_text()
    assert "/etc/falconry/tls/" in shipped
    config = tmp_path / "router.json5"
    config.write_text(shipped.replace("/etc/falconry/tls/", f"{tmp_path / 'tls'}/"))
    endpoint = f"tls/127.0.0.1:{free_port()}"
    unit = parse_unit(render_units(UnitSettings())[ROUTER_UNIT])
    args = exec_start_args(unit, "uav1")[1:]
    args[args.index("--zenoh-config") + 1] = str(config)
    # FALCONRY_TLS_DIR set, as in a shell that read falconry.env: the file, not the variable, decides
    processes.start(*args, "--listen", endpoint, "--connect", f"tls/127.0.0.1:{free_port()}",
                    env=os.environ | {"FALCONRY_TLS_DIR": str(tmp_path / "tls")})
    uav1 = member(tmp_path / "tls", "uav1", endpoint, timeout=30.0)
    uav2 = member(tmp_path / "tls", "uav2", endpoint)
    try:
        statuses, commands = Inbox(uav1, keys.uav("uav2", "status")), Inbox(uav1, keys.uav("uav1", "command"))
        publish_until(lambda: (uav2.put(keys.uav("uav1", "command"), command("uav2/job_manager")),
                               uav2.put(keys.uav("uav2", "status"), status("uav2"))),
                      lambda: statuses.count(keys.uav("uav2", "status")) >= 10)
        assert commands.count(keys.uav("uav1", "command")) == 0
        statuses.close()
        commands.close()
    finally:
        uav2.close()
        uav1.close()


def test_router_config_file_mistakes_are_one_line(tmp_path, capsys):
    plain = str(REPO / "deploy" / "zenoh" / "onboard-router.json5")
    client = tmp_path / "client.json5"
    client.write_text('{ mode: "client" }')
    no_certificates = tmp_path / "router.json5"
    no_certificates.write_text((REPO / "deploy" / "onboard" / "uav1" / "router.json5").read_text()
                               .replace("/etc/falconry/tls/", f"{tmp_path / 'missing'}/"))
    for argv, expected in ((["--zenoh-config", str(tmp_path / "none.json5")], "zenoh config file not found"),
                           (["--zenoh-config", str(client)], "a router's configuration"),
                           (["--zenoh-config", plain, "--tls", str(tmp_path), "--uavs", "2"], "its own TLS"),
                           (["--zenoh-config", str(no_certificates)], "cannot be read")):
        assert main(["router", *argv]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and expected in err, err
