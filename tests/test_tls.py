"""Mutual TLS and the team's access control (services/lib/runtime/tls.py, `falconry certs`, `--tls`).

Certificates are made by the real `falconry certs` into the test's directory; every Zenoh check
runs real sessions on loopback through a router configured by the same code as `falconry router
--tls` (or the checked-in zenohd configs, moved onto the test's ports and certificates):
- a party without a valid certificate (none at all; one of another CA) gets no link: a client's
  open fails, a peer opens alone and never exchanges a message with the team;
- a party holding uav2's certificate cannot publish falconry/uav1/command: a real
  `falconry run planner --uav uav1 --tls` never counts one, while uav2's own keys reach uav1 and a
  command from uav1's own identity does reach the planner (the controls: the path works);
- the simulator speaks for each UAV's flight controller (odometry) but not its job manager;
- two onboard routers peering over mutual TLS carry a partner's own keys and nothing forged;
- a whole seeded lockstep run of the team through the access-controlled router loses nothing.
"""
from __future__ import annotations

import contextlib
import io
import json
import queue
import shutil
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zenoh

from schemas import keys
from schemas.messages import Header, MissionCommand, UavStatus
from services.tools.launcher import cli
from services.tools.registry import node_class
from services.tools.launcher.router_cmd import router_config
from services.lib.runtime import tls
from services.lib.runtime.health import query_health
from services.lib.runtime.zenoh_config import (ZenohConfigError, ZenohSettings, ZenohUnreachable, build, free_port,
                                           open_session)
from tests.tools.run import end_partner
from tests.conftest import REPO, falconry_argv

TEAM = ["uav1", "uav2"]
PLAIN_ONBOARD = REPO / "deploy" / "zenoh" / "onboard-router.json5"
SETTLE_S = 1.0  # after the controls arrived, forbidden messages sent meanwhile had as long to arrive


def falconry(*args: str) -> tuple[int, str, str]:
    """`falconry ARGS` in this process (services.tools.launcher.cli.main): (exit code, stdout, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = cli.main(list(args))
        except SystemExit as exc:  # argparse's own usage errors
            code = exc.code
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def certs(tmp_path_factory) -> Path:
    """The team's certificates (uav1..uav3, sim, ground, router) by `falconry certs`."""
    directory = tmp_path_factory.mktemp("tls") / "team"
    code, out, err = falconry("certs", str(directory), "--uavs", "3", "--days", "2")
    assert code == 0, err
    assert "next:" in out
    return directory


@pytest.fixture(scope="module")
def rogue(tmp_path_factory, certs) -> Path:
    """uav2's certificate from ANOTHER CA, beside the team's ca.crt (which is public): the
    handshake can verify the team's router, the router must refuse the client."""
    other = tmp_path_factory.mktemp("tls") / "other"
    code, _, err = falconry("certs", str(other), "--uavs", "3")
    assert code == 0, err
    mixed = tmp_path_factory.mktemp("tls") / "rogue"
    mixed.mkdir(exist_ok=True)
    shutil.copy(certs / "ca.crt", mixed / "ca.crt")
    for name in ("uav2.crt", "uav2.key"):
        shutil.copy(other / name, mixed / name)
    return mixed


# --------------------------------------------------------------------- helpers
def tls_endpoint(port: int | None = None) -> str:
    return f"tls/127.0.0.1:{port or free_port()}"


@contextlib.contextmanager
def team_router(certs: Path, listen: str, team=TEAM):
    """The router `falconry router --tls DIR --team ...` runs, in this process."""
    config = router_config([listen], tls_dir=str(certs), identity=tls.ROUTER, team=list(team))
    config.insert_json5("transport/shared_memory/enabled", "false")
    router = zenoh.open(config)
    try:
        yield router
    finally:
        router.close()


def deploy_config(relative: str, certs: Path, listen: str, connect: list[str]) -> zenoh.Config:
    """A checked-in TLS router config as shipped, moved onto the test's port and certificates."""
    config = zenoh.Config.from_file(str(REPO / relative))
    for name, value in json.loads(config.get_json("transport/link/tls")).items():
        if isinstance(value, str) and value.startswith(tls.DEPLOY_TLS_DIR + "/"):
            config.insert_json5(f"transport/link/tls/{name}", json.dumps(value.replace(tls.DEPLOY_TLS_DIR, str(certs))))
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    config.insert_json5("connect/endpoints", json.dumps(connect))
    config.insert_json5("transport/shared_memory/enabled", "false")
    return config


def member(certs: Path, identity: str, endpoint: str, timeout: float = 10.0) -> zenoh.Session:
    """A falconry client session presenting `identity`'s certificate."""
    return open_session(ZenohSettings(profile="router", connect=[endpoint], shared_memory=False,
                                      connect_timeout=timeout, tls_dir=str(certs), tls_identity=identity))


class Inbox:
    """Every sample a subscriber gets: (key, payload)."""

    def __init__(self, session: zenoh.Session, key_expr: str) -> None:
        self._lock = threading.Lock()
        self.samples: list[tuple[str, bytes]] = []
        self._sub = session.declare_subscriber(key_expr, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        with self._lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def keys(self) -> list[str]:
        with self._lock:
            return [key for key, _ in self.samples]

    def count(self, key: str, payload: bytes | None = None) -> int:
        with self._lock:
            return sum(1 for k, p in self.samples if k == key and (payload is None or p == payload))

    def close(self) -> None:
        self._sub.undeclare()


def publish_until(send, done, timeout: float = 15.0, period: float = 0.1) -> None:
    """Call send() every period until done() holds (the positive control), then for SETTLE_S more."""
    deadline = time.monotonic() + timeout
    while not done():
        assert time.monotonic() < deadline, "the positive control never arrived: the link itself is broken"
        send()
        time.sleep(period)
    settle = time.monotonic() + SETTLE_S
    while time.monotonic() < settle:
        send()
        time.sleep(period)
    time.sleep(SETTLE_S)


def allowed(acl: dict, identity: str, flow: str, message: str, key: str) -> bool:
    """The decision Zenoh's ACL makes (zenoh/src/net/routing/interceptor/authorization.rs): the
    subject's deny rules whose key expressions include the key win, then its allow rules, else the
    default; a subject with no policy gets the default."""
    subjects = {s["id"] for s in acl["subjects"] if identity in s["cert_common_names"]}
    rule_ids = {r for p in acl["policies"] if subjects & set(p["subjects"]) for r in p["rules"]}
    rules = [r for r in acl["rules"] if r["id"] in rule_ids and flow in r["flows"] and message in r["messages"]
             and any(zenoh.KeyExpr(e).includes(zenoh.KeyExpr(key)) for e in r["key_exprs"])]
    if any(r["permission"] == "deny" for r in rules):
        return False
    return acl["default_permission"] == "allow" or any(r["permission"] == "allow" for r in rules)


def command(sender: str, action: str = "emergency_land") -> bytes:
    return msgspec.msgpack.encode(MissionCommand(header=Header(sender=sender, seq=1), command_id=1, action=action))


def status(uav: str) -> bytes:
    return msgspec.msgpack.encode(UavStatus(header=Header(sender=f"{uav}/job_manager"), uav=uav, state="IDLE",
                                            flying_normally=True, airborne=False, position=(0.0, 0.0, 0.0)))


# ---------------------------------------------------------------- pure functions
def test_identities_and_file_layout():
    assert tls.identities(["uav1", "uav2"]) == ["uav1", "uav2", "sim", "ground", "router"]
    assert tls.identity_for("planner", "uav1") == "uav1"
    assert tls.identity_for("simulator", None) == "sim"
    assert tls.identity_for(None, "uav1") == "ground"  # a ground tool, even one naming a UAV (colors)
    with pytest.raises(tls.TlsError, match="per-UAV service"):
        tls.identity_for("planner", None)
    files = tls.files("/d", "uav2")
    assert files == tls.TlsFiles(Path("/d/ca.crt"), Path("/d/uav2.crt"), Path("/d/uav2.key"))
    assert tls.ca_key("/d") == Path("/d/ca.key")
    for bad in ("ca", "UAV1", "a b", ""):
        with pytest.raises(tls.TlsError):
            tls.check_identity(bad)


@pytest.mark.parametrize("team, error", [([], "at least one UAV"), (["uav1", "uav1"], "twice"),
                                         (["uav1", "ground"], "cannot be named"), (["uav1", "sim"], "invalid UAV"),
                                         (["Uav1"], "invalid UAV")])
def test_a_bad_team_is_refused(team, error):
    with pytest.raises(tls.TlsError, match=error):
        tls.check_team(team)


def test_certificate_names_serve_loopback_the_radio_and_compose():
    assert tls.host_names("uav1") == (["uav1", "uav1.radio", "localhost"], ["127.0.0.1"])
    assert tls.host_names("router") == (["router", "zenoh", "localhost"], ["127.0.0.1"])
    assert tls.host_names("sim", ["gcs.local", "10.0.0.7", "127.0.0.1"]) == (
        ["sim", "localhost", "gcs.local"], ["127.0.0.1", "10.0.0.7"])
    with pytest.raises(tls.TlsError):
        tls.host_names("sim", ["bad host"])


@pytest.mark.parametrize("identity, flow, message, key, expected", [
    ("uav1", "ingress", "put", "falconry/uav1/command", True),
    ("uav2", "ingress", "put", "falconry/uav1/command", False),
    ("uav2", "ingress", "put", "falconry/uav2/status", True),
    ("uav2", "ingress", "delete", "falconry/uav1/status", False),
    ("uav2", "ingress", "liveliness_token", "falconry/uav1/alive/planner", False),
    ("uav2", "ingress", "declare_queryable", "falconry/uav1/health/planner", False),
    ("uav2", "ingress", "reply", "falconry/uav1/health/planner", False),
    ("uav2", "ingress", "declare_subscriber", "falconry/*/status", True),
    ("uav2", "ingress", "query", "falconry/*/health/*", True),
    ("uav2", "ingress", "put", "falconry/sim/clock", False),
    ("uav2", "egress", "put", "falconry/uav1/status", True),
    ("uav2", "ingress", "put", "elsewhere/key", False),
    ("uav2", "ingress", "declare_subscriber", "**", False),
    ("uav3", "ingress", "put", "falconry/uav3/status", False),  # not in this team
    ("sim", "ingress", "put", "falconry/uav1/odometry", True),
    ("sim", "ingress", "put", "falconry/uav1/imu", True),
    ("sim", "ingress", "put", "falconry/sim/clock", True),
    ("sim", "ingress", "put", "falconry/uav1/command", False),
    ("sim", "ingress", "put", "falconry/uav1/trajectory", False),
    ("ground", "ingress", "put", "falconry/uav2/colors", True),
    ("ground", "ingress", "put", "falconry/uav2/command", False),
    ("ground", "ingress", "put", "falconry/sim/clock", False),
    ("ground", "ingress", "query", "falconry/*/health/*", True),
    ("router", "ingress", "declare_subscriber", "falconry/**", False),
    ("router", "egress", "put", "falconry/uav1/status", False),
    ("mallory", "egress", "put", "falconry/uav1/status", False),
])
def test_access_control_decisions(identity, flow, message, key, expected):
    assert allowed(tls.access_control(TEAM), identity, flow, message, key) is expected


class _Handle:
    def undeclare(self) -> None:
        pass

    def put(self, *args, **kwargs) -> None:
        pass


class _Declarations:
    """A stand-in session that only records what a node declares: (ACL message, key)."""

    def __init__(self) -> None:
        self.made: list[tuple[str, str]] = []
        outer = self

        class Liveliness:
            def declare_subscriber(self, key, *args, **kwargs):
                outer.made.append(("declare_liveliness_subscriber", str(key)))
                return _Handle()

        self._liveliness = Liveliness()

    def liveliness(self):
        return self._liveliness

    def declare_publisher(self, key, **kwargs):
        self.made.append(("put", str(key)))
        return _Handle()

    def declare_subscriber(self, key, *args, **kwargs):
        self.made.append(("declare_subscriber", str(key)))
        return _Handle()

    def declare_queryable(self, key, *args, **kwargs):
        self.made += [("declare_queryable", str(key)), ("reply", str(key))]  # it answers on its own key
        return _Handle()


@pytest.mark.parametrize("service", keys.SERVICES)
def test_the_access_control_admits_everything_each_service_declares(service):
    """Every publisher, subscriber, queryable and the liveliness token of the real node classes,
    checked against the team's ACL for the identity that service presents (the simulator's
    per-UAV odometry and IMU included): the ACL cannot starve the team."""
    parser = cli.build_parser()
    argv = ["run", service] + (["--uavs", "2"] if service in keys.SIM_SERVICES else ["--uav", "uav1"])
    args = parser.parse_args(argv)
    node = node_class(service)(args.uav, ZenohSettings(), options=args)
    node.session = _Declarations()
    node.declare()
    made = node.session.made + [("liveliness_token", keys.alive(node.scope, service))]
    identity = tls.identity_for(service, args.uav)
    acl = tls.access_control(TEAM)
    refused = [(m, k) for m, k in made if not allowed(acl, identity, "ingress", m, k)]
    assert not refused, f"{service} as {identity}: {refused}"
    assert len({m for m, _ in made}) >= 4
    if service == "simulator":  # it stands in for each UAV's flight controller
        flight_controllers = {keys.uav(u, t) for u in TEAM for t in keys.FLIGHT_CONTROLLER_TOPICS}
        assert {k for m, k in made if m == "put"} >= flight_controllers
    # what `falconry sim`'s launcher (identity sim) declares besides: run events, the resume queryable
    for message, key in (("put", keys.EVENTS), ("declare_queryable", keys.RESUME), ("reply", keys.RESUME)):
        assert allowed(acl, tls.SIM, "ingress", message, key)


def test_router_settings_need_both_certificates_and_team():
    files = tls.files("/d", "router")
    with pytest.raises(tls.TlsError):
        tls.router_inserts(["tls/0.0.0.0:7447"], tls_files=files)
    with pytest.raises(tls.TlsError):
        tls.router_inserts(["tls/0.0.0.0:7447"], team=TEAM)
    plain = tls.router_inserts(["tcp/0.0.0.0:7447"])
    assert "access_control" not in plain and not any(k.startswith("transport/link/tls") for k in plain)
    secured = tls.router_inserts(["tls/0.0.0.0:7447"], ["tls/uav2.radio:7447"], 3000, files, TEAM)
    assert secured["transport/link/tls/enable_mtls"] is True
    assert secured["access_control"]["default_permission"] == "deny"
    assert tls.nest({"a/b": 1, "a/c/d": 2, "e": 3}) == {"a": {"b": 1, "c": {"d": 2}}, "e": 3}


# ------------------------------------------------------------- session settings
def test_session_settings_with_tls(certs):
    settings = ZenohSettings(profile="router", connect=["tls/127.0.0.1:7447"], tls_dir=str(certs), tls_identity="uav1")
    config = build(settings)
    assert json.loads(config.get_json("transport/link/tls/connect_certificate")) == str(certs / "uav1.crt")
    assert json.loads(config.get_json("transport/link/tls/root_ca_certificate")) == str(certs / "ca.crt")
    assert json.loads(config.get_json("transport/link/tls/enable_mtls")) is True
    assert "mutual TLS as uav1" in settings.describe()
    # the defaults become tls/ too
    assert json.loads(build(ZenohSettings(profile="router", tls_dir=str(certs), tls_identity="ground"))
                      .get_json("connect/endpoints")) == ["tls/127.0.0.1:7447"]
    assert json.loads(build(ZenohSettings(tls_dir=str(certs), tls_identity="sim"))
                      .get_json("listen/endpoints")) == ["tls/127.0.0.1:0"]
    # a child (falconry sim) gets the same settings back
    args = cli.build_parser().parse_args(["run", "planner", "--uav", "uav1", *settings.as_args()])
    assert (args.tls, args.tls_identity, args.connect) == (str(certs), "uav1", ["tls/127.0.0.1:7447"])


@pytest.mark.parametrize("argv, identity", [
    (["run", "planner", "--uav", "uav2"], "uav2"),
    (["run", "simulator"], "sim"),
    (["run", "planner", "--uav", "uav2", "--tls-identity", "uav1"], "uav1"),
    (["health", "--zenoh-profile", "router"], "ground"),
    (["record", "/tmp/x.mcap"], "ground"),
    (["view", "--connect", "tls/127.0.0.1:7447"], "ground"),
    (["replay", "/tmp/x.mcap"], "ground"),
    (["colors", "pick", "x.png", "--roi", "1,1,2,2", "--uav", "uav1"], "ground"),
    (["sim"], "sim"),
])
def test_each_command_presents_its_identity(certs, argv, identity):
    from services.tools.launcher.common import zenoh_settings
    args = cli.build_parser().parse_args([*argv, "--tls", str(certs)])
    assert zenoh_settings(args).tls_identity == identity
    assert zenoh_settings(cli.build_parser().parse_args([*argv, "--tls", ""])).tls_dir is None


def test_tls_dir_defaults_to_the_environment(certs, monkeypatch):
    monkeypatch.setenv(tls.ENV_DIR, str(certs))
    assert cli.build_parser().parse_args(["health"]).tls == str(certs)
    monkeypatch.setenv(tls.ENV_DIR, "")
    assert cli.build_parser().parse_args(["health"]).tls is None


def test_session_mistakes_are_usage_errors(certs, tmp_path):
    with pytest.raises(ZenohConfigError, match="every endpoint is tls/"):
        build(ZenohSettings(profile="router", connect=["tcp/127.0.0.1:7447"], tls_dir=str(certs), tls_identity="uav1"))
    with pytest.raises(ZenohConfigError, match="every endpoint is tls/"):
        build(ZenohSettings(listen=["tcp/127.0.0.1:0"], tls_dir=str(certs), tls_identity="uav1"))
    partial = tmp_path / "partial"
    partial.mkdir()
    shutil.copy(certs / "ca.crt", partial)
    shutil.copy(certs / "uav1.crt", partial)
    with pytest.raises(ZenohConfigError, match=r"uav1\.key is missing"):
        build(ZenohSettings(profile="router", tls_dir=str(partial), tls_identity="uav1"))
    (partial / "uav1.key").write_text("not a key\n")
    with pytest.raises(ZenohConfigError, match=r"uav1\.key is not a PEM"):
        build(ZenohSettings(profile="router", tls_dir=str(partial), tls_identity="uav1"))
    (partial / "uav1.key").unlink()
    (partial / "uav1.key").mkdir()  # unreadable as a file, even for root
    with pytest.raises(ZenohConfigError, match=r"cannot read .*uav1\.key"):
        build(ZenohSettings(profile="router", tls_dir=str(partial), tls_identity="uav1"))
    with pytest.raises(ZenohConfigError, match="no such directory"):
        build(ZenohSettings(profile="router", tls_dir=str(tmp_path / "none"), tls_identity="uav1"))


@pytest.mark.parametrize("argv, expected", [
    (["run", "planner", "--uav", "uav1", "--zenoh-profile", "router", "--connect", "tcp/127.0.0.1:9"],
     "every endpoint is tls/"),
    (["run", "planner", "--uav", "uav9", "--zenoh-profile", "router", "--connect", "tls/127.0.0.1:9"],
     "uav9.crt is missing"),
    (["health", "--connect", "tls/127.0.0.1:9", "--tls-identity", "Nobody"], "invalid TLS identity"),
    (["router"], "give the team"),
    (["router", "--uavs", "2", "--listen", "tcp/127.0.0.1:9"], "every endpoint is tls/"),
    (["router", "--uavs", "2", "--tls-identity", "uav7"], "--tls-identity uav7"),
    (["router", "--team", "uav1,UAV2"], "invalid UAV name"),
    (["router", "--uavs", "2", "--lease-ms", "0"], "--lease-ms must be positive"),
    (["sim", "--isolate"], "namespaces"),
])
def test_tls_mistakes_give_one_line_and_exit_2(certs, argv, expected):
    result = subprocess.run(falconry_argv(*argv, "--tls", str(certs)), cwd=REPO, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and expected in errors[0], result.stderr


def test_a_team_without_tls_is_refused():
    code, _, err = falconry("router", "--uavs", "2")
    assert code == 2 and "--tls DIR and the team" in err


# ---------------------------------------------------------------- falconry certs
def test_certs_makes_a_ca_and_one_certificate_per_identity(tmp_path):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    directory = tmp_path / "certs"
    code, out, err = falconry("certs", str(directory), "--team", "red,blue", "--host", "10.1.2.3", "--host", "gcs")
    assert code == 0, err
    assert f"falconry router --listen tls/0.0.0.0:7447 --tls {directory} --team red,blue" in out
    ca = x509.load_pem_x509_certificate((directory / "ca.crt").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    assert oct((directory / "ca.key").stat().st_mode & 0o777) == "0o600"
    for identity in ("red", "blue", "sim", "ground", "router"):
        cert = x509.load_pem_x509_certificate((directory / f"{identity}.crt").read_bytes())
        cert.verify_directly_issued_by(ca)
        assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == identity
        names = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        dns, ips = tls.host_names(identity, ["10.1.2.3", "gcs"])
        assert names.get_values_for_type(x509.DNSName) == dns
        assert [str(ip) for ip in names.get_values_for_type(x509.IPAddress)] == ips
        assert oct((directory / f"{identity}.key").stat().st_mode & 0o777) == "0o600"
        assert f"CN {identity};" in out
    assert "red.radio" in tls.host_names("red")[0]
    # an existing CA is kept unless --force
    before = (directory / "ca.crt").read_bytes()
    code, _, err = falconry("certs", str(directory), "--uavs", "2")
    assert code == 2 and "ca.crt exists" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert (directory / "ca.crt").read_bytes() == before
    code, _, err = falconry("certs", str(directory), "--uavs", "2", "--force")
    assert code == 0, err
    assert (directory / "ca.crt").read_bytes() != before


@pytest.mark.parametrize("argv, expected", [
    (["--uavs", "0"], "--uavs must be 1 or more"),
    (["--team", "uav1,ground"], "cannot be named"),
    (["--team", "uav1", "--uavs", "2"], "not allowed with argument"),
    (["--days", "0"], "--days must be from 1 to 36500"),
    (["--days", "10000000"], "--days must be from 1 to 36500"),
    (["--host", "no/slash"], "invalid host name"),
])
def test_certs_mistakes_give_one_line_and_exit_2(tmp_path, argv, expected):
    result = subprocess.run(falconry_argv("certs", str(tmp_path / "c"), *argv), cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert result.returncode == 2, result.stderr
    assert "Traceback" not in result.stderr
    errors = [line for line in result.stderr.splitlines() if "error" in line]
    assert len(errors) == 1 and expected in errors[0], result.stderr


# --------------------------------------------------------------- deploy configs
def test_checked_in_tls_configs_are_the_generators_output():
    generated = tls.deploy_configs()
    assert set(generated) == {"deploy/zenoh/router-tls.json5", "deploy/onboard/uav1/router.json5",
                              "deploy/onboard/uav2/router.json5", "deploy/onboard/uav3/router.json5"}
    for relative, text in generated.items():
        path = REPO / relative
        assert path.read_text() == text, f"{relative} is stale: run `{tls.GENERATED_BY}`"
        assert tls.GENERATED_BY in path.read_text().splitlines()[0]
        config = zenoh.Config.from_file(str(path))
        get = lambda key: json.loads(config.get_json(key))  # noqa: E731
        assert get("mode") == "router"
        assert get("listen/endpoints") == ["tls/0.0.0.0:7447"]
        assert get("scouting/multicast/enabled") is False
        assert get("transport/link/tls/enable_mtls") is True
        assert get("transport/link/tls/verify_name_on_connect") is True
        assert get("transport/link/tls/root_ca_certificate") == "/etc/falconry/tls/ca.crt"
        acl = get("access_control")
        assert acl["enabled"] is True and acl["default_permission"] == "deny"
        assert without_nulls(acl) == tls.access_control(["uav1", "uav2", "uav3"])  # as Zenoh read it
    compose = zenoh.Config.from_file(str(REPO / "deploy/zenoh/router-tls.json5"))
    assert json.loads(compose.get_json("transport/link/tls/listen_certificate")) == "/etc/falconry/tls/router.crt"
    plain = zenoh.Config.from_file(str(PLAIN_ONBOARD))
    for uav in ("uav1", "uav2", "uav3"):
        onboard = zenoh.Config.from_file(str(REPO / f"deploy/onboard/{uav}/router.json5"))
        get = lambda key: json.loads(onboard.get_json(key))  # noqa: E731
        assert get("connect/endpoints") == [f"tls/{u}.radio:7447" for u in ("uav1", "uav2", "uav3") if u != uav]
        assert get("transport/link/tls/connect_certificate") == f"/etc/falconry/tls/{uav}.crt"
        assert get("transport/link/tls/listen_private_key") == f"/etc/falconry/tls/{uav}.key"
        # the same link behaviour as the plain onboard router
        for key in ("transport/link/tx/lease", "transport/link/tx/keep_alive", "connect/retry",
                    "connect/timeout_ms", "connect/exit_on_failure", "scouting/gossip/enabled"):
            assert get(key) == json.loads(plain.get_json(key)), key


def without_nulls(value):
    """A config section as given: Zenoh fills the fields left out with null."""
    if isinstance(value, dict):
        return {k: without_nulls(v) for k, v in value.items() if v is not None}
    if isinstance(value, list):
        return [without_nulls(v) for v in value]
    return value


def test_the_generator_reports_stale_files():
    assert tls.main(["write-deploy-configs", "--check"]) == 0
    assert tls.main(["bogus"]) == 2


# ------------------------------------------------------------------ real sessions
def test_a_party_without_a_valid_certificate_cannot_connect(certs, rogue):
    endpoint = tls_endpoint()
    with team_router(certs, endpoint) as router:
        uav1 = member(certs, "uav1", endpoint)
        uav2 = member(certs, "uav2", endpoint)
        inbox = Inbox(uav1, f"{keys.ROOT}/**")
        try:
            # a client with no certificate (it trusts the team CA): the router refuses the handshake
            bare = zenoh.Config()
            for path, value in (("mode", "client"), ("connect/endpoints", [endpoint]),
                                ("scouting/multicast/enabled", False),
                                ("transport/link/tls/root_ca_certificate", str(certs / "ca.crt"))):
                bare.insert_json5(path, json.dumps(value))
            with pytest.raises(zenoh.ZError, match="Unable to connect"):
                zenoh.open(bare).close()
            # plain tcp to the TLS port
            with pytest.raises(ZenohUnreachable):
                open_session(ZenohSettings(profile="router", connect=[endpoint.replace("tls/", "tcp/")],
                                           shared_memory=False, connect_timeout=0))
            # uav2's name, certified by another CA, through falconry's own session code
            with pytest.raises(ZenohUnreachable, match="Unable to connect"):
                member(rogue, "uav2", endpoint, timeout=1.0)
            # the same certificate as a peer: Zenoh opens a peer regardless, but alone: no link,
            # nothing it publishes arrives, nothing the team publishes reaches it
            peer = open_session(ZenohSettings(connect=[endpoint], listen=["tls/127.0.0.1:0"], shared_memory=False,
                                              tls_dir=str(rogue), tls_identity="uav2"))
            try:
                overheard = Inbox(peer, f"{keys.ROOT}/**")
                publish_until(lambda: (peer.put(keys.uav("uav2", "status"), b"rogue"),
                                       uav2.put(keys.uav("uav2", "status"), b"member"),
                                       uav1.put(keys.uav("uav1", "status"), b"member")),
                              lambda: inbox.count(keys.uav("uav2", "status"), b"member") >= 5)
                assert list(peer.info.routers_zid()) == [] and list(peer.info.peers_zid()) == []
                assert inbox.count(keys.uav("uav2", "status"), b"rogue") == 0
                assert overheard.count(keys.uav("uav1", "status")) == 0
                assert overheard.count(keys.uav("uav2", "status"), b"member") == 0
                assert overheard.count(keys.uav("uav2", "status"), b"rogue") > 0  # its own, locally: it listens
                overheard.close()
            finally:
                peer.close()
            assert list(router.info.peers_zid()) == []  # routers list peers; clients are not peers
        finally:
            inbox.close()
            uav2.close()
            uav1.close()


@pytest.mark.alone  # a wall-clock planner asked for its health within 2 s
def test_uav2_cannot_command_uav1s_planner_but_publishes_its_own_keys(certs, processes):
    """The issue's acceptance: through `falconry router --tls`, a party with uav2's certificate
    publishes falconry/uav1/command and uav1's real planner never counts one, nor does any uav1
    subscriber; uav2's own status reaches uav1 meanwhile, and a command from uav1's own identity
    reaches the planner (so the planner would have counted uav2's)."""
    endpoint = tls_endpoint()
    router = processes.start("router", "--listen", endpoint, "--tls", str(certs), "--team", ",".join(TEAM),
                             "--exit-with-parent")
    ground = member(certs, "ground", endpoint, timeout=30.0)
    uav1 = uav2 = None
    try:
        planner = processes.start("run", "planner", "--uav", "uav1", "--clock", "wall", "--zenoh-profile", "router",
                                  "--connect", endpoint, "--tls", str(certs), "--exit-with-parent")
        deadline = time.monotonic() + 60
        while not list(ground.liveliness().get(keys.alive("uav1", "planner"), timeout=1.0)):
            assert planner.poll() is None and router.poll() is None, "planner or router exited"
            assert time.monotonic() < deadline, "uav1's planner never came up"
            time.sleep(0.2)
        uav1 = member(certs, "uav1", endpoint)
        uav2 = member(certs, "uav2", endpoint)
        watch = Inbox(uav1, keys.ALL_STATUS)  # what uav1's job manager listens to
        commands = Inbox(uav1, keys.uav("uav1", "command"))
        forged = command("uav2/job_manager")
        publish_until(lambda: (uav2.put(keys.uav("uav1", "command"), forged),
                               uav2.put(keys.uav("uav2", "status"), status("uav2"))),
                      lambda: watch.count(keys.uav("uav2", "status")) >= 10)
        assert commands.count(keys.uav("uav1", "command")) == 0

        def arrived(key: str) -> int:
            (h,) = [h for h in query_health(ground, 2.0) if (h.uav, h.service) == ("uav1", "planner")]
            return sum(counter.get(key, 0) for counter in (h.received, h.decode_errors, h.dropped_stale,
                                                           h.dropped_backlog))

        assert "falconry/uav1/command" in [h for h in query_health(ground, 2.0)
                                           if h.service == "planner"][0].subscriptions
        assert arrived(keys.uav("uav1", "command")) == 0, "a command from uav2 reached uav1's planner"
        # the control: uav1's own job manager identity is heard by the planner
        deadline = time.monotonic() + 15
        sent = 0
        while arrived(keys.uav("uav1", "command")) == 0:
            assert time.monotonic() < deadline, "not even uav1's own command reached its planner"
            uav1.put(keys.uav("uav1", "command"), command("uav1/job_manager", "hover"))
            sent += 1
            time.sleep(0.3)
        assert arrived(keys.uav("uav1", "command")) <= sent  # ... and only those
        assert commands.count(keys.uav("uav1", "command"), forged) == 0
        watch.close()
        commands.close()
    finally:
        for session in (uav2, uav1, ground):
            if session is not None:
                session.close()


def test_the_simulator_speaks_for_the_flight_controller_only(certs):
    """Through the compose router's checked-in TLS config (what zenohd runs): deploy/zenoh/router-tls.json5."""
    endpoint = tls_endpoint()
    router = zenoh.open(deploy_config(tls.COMPOSE_CONFIG, certs, endpoint, []))
    try:
        uav1, sim, ground = (member(certs, identity, endpoint) for identity in ("uav1", "sim", "ground"))
        inbox = Inbox(uav1, f"{keys.ROOT}/**")
        try:
            def send() -> None:
                sim.put(keys.uav("uav1", keys.ODOMETRY), b"sim")
                sim.put(keys.CLOCK, b"sim")
                sim.put(keys.uav("uav1", "command"), b"sim")
                sim.put(keys.uav("uav1", "status"), b"sim")
                ground.put(keys.uav("uav1", keys.COLORS), b"ground")
                ground.put(keys.uav("uav1", "command"), b"ground")
                ground.put(keys.FAULTS, b"ground")

            publish_until(send, lambda: min(inbox.count(keys.uav("uav1", keys.ODOMETRY)), inbox.count(keys.CLOCK),
                                            inbox.count(keys.uav("uav1", keys.COLORS))) >= 5)
            assert set(inbox.keys()) == {keys.uav("uav1", keys.ODOMETRY), keys.CLOCK, keys.uav("uav1", keys.COLORS)}
            # health answers come back from every party, asked by anyone
            token = sim.declare_queryable(keys.health(keys.SIM, "simulator"),
                                          lambda q: q.reply(keys.health(keys.SIM, "simulator"), b"ok"))
            replies = []
            deadline = time.monotonic() + 10
            while not replies and time.monotonic() < deadline:
                replies = [str(r.ok.key_expr) for r in ground.get(keys.health("*", "*"), timeout=1.0) if r.ok]
            token.undeclare()
            assert replies == [keys.health(keys.SIM, "simulator")]
        finally:
            inbox.close()
            for session in (ground, sim, uav1):
                session.close()
    finally:
        router.close()


PARTNER = textwrap.dedent("""
    # uav2's onboard router (its deploy config, moved onto the test's port and certificates) with
    # uav2's services, a uav1 certificate holder connected to it, and the router's own session.
    import json, select, sys, zenoh
    from services.lib.runtime.zenoh_config import ZenohSettings, open_session
    path, certs, listen, connect = sys.argv[1:5]
    config = zenoh.Config.from_file(path)
    config.insert_json5("listen/endpoints", json.dumps([listen]))
    config.insert_json5("connect/endpoints", json.dumps([connect]))
    config.insert_json5("transport/shared_memory/enabled", "false")
    for name, value in json.loads(config.get_json("transport/link/tls")).items():
        if isinstance(value, str) and value.startswith("/etc/falconry/tls/"):
            config.insert_json5(f"transport/link/tls/{name}", json.dumps(value.replace("/etc/falconry/tls", certs)))
    router = zenoh.open(config)
    def client(identity):
        return open_session(ZenohSettings(profile="router", connect=[listen], shared_memory=False,
                                          connect_timeout=10, tls_dir=certs, tls_identity=identity))
    uav2, impostor = client("uav2"), client("uav1")
    heard = []
    sub = uav2.declare_subscriber("falconry/uav1/status", lambda s: heard.append(1))
    token = uav2.liveliness().declare_token("falconry/uav2/alive/job_manager")
    print("ready", flush=True)
    said = False
    while True:  # until the test closes our stdin
        if select.select([sys.stdin], [], [], 0.1)[0] and not sys.stdin.readline():
            break
        uav2.put("falconry/uav2/status", b"uav2's own")
        uav2.put("falconry/uav1/command", b"uav2's client")  # refused by uav2's own router
        router.put("falconry/uav1/command", b"uav2's router")  # a compromised partner router
        impostor.put("falconry/uav1/command", b"uav1's name via uav2's router")
        if heard and not said:
            print("heard uav1", flush=True)
            said = True
    sub.undeclare(); token.undeclare()
    impostor.close(); uav2.close(); router.close()
""")


def test_onboard_routers_carry_a_partners_own_keys_only(certs):
    """uav1's and uav2's onboard routers (deploy/onboard/*, moved onto loopback ports and the
    test's certificates) peer over mutual TLS. uav1's router admits from uav2's router only what
    is uav2's: uav2's status and liveliness pass; a falconry/uav1/command forged by uav2's router
    itself, or published through it by a uav1 certificate holder, never reaches uav1."""
    here, there = tls_endpoint(), tls_endpoint()
    router = zenoh.open(deploy_config(tls.onboard_config_path("uav1"), certs, here, [there]))
    uav1 = member(certs, "uav1", here)
    inbox = Inbox(uav1, f"{keys.ROOT}/**")
    tokens: queue.SimpleQueue = queue.SimpleQueue()
    watcher = uav1.liveliness().declare_subscriber(keys.ALL_ALIVE, lambda s: tokens.put(str(s.key_expr)),
                                                   history=True)
    partner = subprocess.Popen([sys.executable, "-c", PARTNER, str(REPO / tls.onboard_config_path("uav2")),
                                str(certs), there, here], cwd=REPO, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                               text=True)
    try:
        assert partner.stdout.readline().strip() == "ready"
        heard: list[str] = []
        reader = threading.Thread(target=lambda: heard.extend(partner.stdout), daemon=True)
        reader.start()
        publish_until(lambda: uav1.put(keys.uav("uav1", "status"), b"uav1's own"),
                      lambda: inbox.count(keys.uav("uav2", "status"), b"uav2's own") >= 10
                      and any("heard uav1" in line for line in heard), timeout=30)
        assert tokens.get(timeout=5) == keys.alive("uav2", "job_manager")
        assert inbox.count(keys.uav("uav1", "command")) == 0, inbox.samples[-5:]
        assert set(inbox.keys()) == {keys.uav("uav1", "status"), keys.uav("uav2", "status")}
    finally:
        end_partner(partner)
        watcher.undeclare()
        inbox.close()
        uav1.close()
        router.close()


@pytest.mark.slow(26)
def test_a_seeded_lockstep_team_runs_whole_through_the_access_controlled_router(certs, tmp_path):
    """`falconry sim --tls --zenoh-profile router`: every service of two UAVs and the simulator,
    each with its own certificate, through the run's own `falconry router --tls --team`. In
    lockstep a single refused tick, acknowledgement, message or liveliness token shows as a
    lockstep wait given up or a lost own-UAV message; none is, and every service answers health."""
    summary = tmp_path / "summary.json"
    result = subprocess.run(
        falconry_argv("sim", "--tls", str(certs), "--zenoh-profile", "router", "--uavs", "2", "--lockstep",
                      "--duration", "3", "--quiet", "--progress", "0", "--summary-json", str(summary),
                      "--wall-timeout", "240"),
        cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert "Traceback" not in result.stderr
    report = json.loads(summary.read_text())
    assert report["finished"] and report["lockstep"]
    health = report["health"]
    assert health["services_answering"] == 1 + 2 * len(keys.uav_services())
    for counter in ("lockstep_timeouts", "lost_own_uav", "decode_errors", "handler_errors", "dropped_stale"):
        assert health[counter] == 0, (counter, health)
    assert report["failed_services"] == [] and report["restarts"] == []
    assert "tls/127.0.0.1:" in result.stdout + result.stderr


@pytest.mark.parametrize("command", ["certs", "router"])
def test_help_explains_the_security_options(command):
    result = subprocess.run(falconry_argv(command, "--help"), cwd=REPO, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0
    lines = result.stdout.splitlines()
    for line in lines:  # every option line carries an explanation (on it or on the next line)
        if line.strip().startswith("--") and len(line.split()) < 3:
            following = lines[lines.index(line) + 1]
            assert following.startswith(" " * 10) and following.strip(), f"undocumented option: {line}"
    expected = {"certs": ["--uavs", "--team", "--days", "--host", "--force"],
                "router": ["--tls", "--tls-identity", "--uavs", "--team", "--connect", "--lease-ms"]}[command]
    assert all(option in result.stdout for option in expected)


def test_the_security_sections_commands_are_valid():
    """Every `falconry` command line of deploy/README.md's security section parses."""
    text = (REPO / "deploy" / "README.md").read_text()
    section = text[text.index("## Security: mutual TLS and access control"):]
    section = section[:section.index("\n## ", 1)]
    commands = [line.split("#")[0].split() for line in section.splitlines() if line.startswith("falconry ")]
    assert len(commands) >= 8
    for argv in commands:
        stderr = io.StringIO()
        try:
            with contextlib.redirect_stderr(stderr):
                cli.build_parser().parse_args(argv[1:])
        except SystemExit:
            pytest.fail(f"`{' '.join(argv)}` is rejected: {stderr.getvalue()}")


@pytest.mark.parametrize("profile", ["router", "embedded"])
def test_falconry_sim_hands_tls_to_every_process(certs, profile):
    """`falconry sim --tls`: tls/ endpoints everywhere, each child derives its own identity from
    its command line, the launcher is sim, and the run's own router enforces the team's ACL."""
    from services.tools.launcher.plan import plan_run

    args = cli.build_parser().parse_args(["sim", "--tls", str(certs), "--zenoh-profile", profile, "--viz", "web"])
    plan = plan_run(args, TEAM, seed=1, duration=3.0, port=7999, network=None)
    assert plan.hub_settings.tls_dir == str(certs) and plan.hub_settings.tls_identity == tls.SIM
    assert all(e.startswith("tls/") for e in plan.hub_settings.connect + plan.hub_settings.listen)
    if profile == "router":
        assert plan.router[plan.router.index("--tls") + 1] == str(certs)
        assert plan.router[plan.router.index("--team") + 1] == ",".join(TEAM)
        assert plan.router[plan.router.index("--listen") + 1] == "tls/127.0.0.1:7999"
    else:
        assert plan.router is None
    from services.tools.launcher.common import zenoh_settings
    children = dict(plan.children, viewer=plan.viewer)
    for name, argv in children.items():
        child = cli.build_parser().parse_args(argv[argv.index("--log-level") + 2:])
        settings = zenoh_settings(child)
        assert settings.tls_dir == str(certs), name
        expected = "ground" if name == "viewer" else name.split("/")[0]
        assert settings.tls_identity == expected, name
        assert all(e.startswith("tls/") for e in settings.connect + settings.listen), (name, settings)
