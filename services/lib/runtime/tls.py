"""Mutual TLS and access control for a Falconry team: identities, certificate files, and the
Zenoh configuration that makes a router admit only the team and each member only to its keys.

Identities (a certificate's common name, CN):
- each UAV's name (uav1, uav2, ...): every service of that UAV (`falconry run SERVICE --uav uav1`),
  and that UAV's onboard router when it peers with the partners' routers over the radio;
- "sim": the simulator, which stands in for every UAV's flight controller (and `falconry sim`'s
  launcher, which publishes run events and answers the simulator's resume query);
- "ground": the ground tools (`falconry record`, `view`, `health`, `replay`, `colors`);
- "router": the compose router (zenohd), which only listens and so needs no permissions.

A TLS directory holds ca.crt (the team's CA, which every party trusts) and <identity>.crt and
<identity>.key per identity; ca.key stays with whoever signs certificates (`falconry certs`). A
UAV needs only ca.crt and its own pair.

Access control (`access_control`): Zenoh enforces it in the router on every link, per message,
by the remote's certificate CN. Default deny, and
- every member (each UAV, sim, ground) may *receive* everything under falconry/** (flow egress:
  data, replies, liveliness tokens, and the declarations and queries a router passes on) and
  *ask* for anything under falconry/** (ingress: declare subscribers and liveliness subscribers,
  queries and liveliness queries). Reading is not what the team guards against: a partner's
  status and tracks, the sim clock and every health answer are read across UAVs by design.
- a UAV may *publish* (ingress put, delete, liveliness token, queryable, reply) only under
  falconry/<its uav>/**: its services' data, acknowledgements, health answers and liveliness.
- sim may publish only falconry/sim/** (clock, world, truth, events, faults, resume, its own
  health/ack/alive) and each team UAV's flight-controller keys, falconry/<uav>/odometry and
  falconry/<uav>/imu (keys.FLIGHT_CONTROLLER_TOPICS, what the simulator publishes for each UAV).
- ground may publish only each team UAV's falconry/<uav>/colors (keys.COLORS, a live colour file
  from `falconry colors pick --send`). Health is a query (an ask). `falconry replay` is NOT
  granted: it publishes sensor data, odometry, the clock and liveliness tokens on behalf of
  UAVs and the simulator, which is exactly what the ACL exists to stop; replay on a lab
  network without --tls (or as the identity whose keys it replays, --tls-identity).
- router has no policy: a party presenting the router's certificate is denied everything.
- a certificate from another CA never gets a link (the TLS handshake fails); a link without a
  certificate common name (e.g. a plain tcp/ listener added by hand) matches no subject and
  is denied everything.

Onboard routers peer over the radio with mutual TLS, each authenticating with its UAV's
certificate and carrying the same team ACL: on uav1's router, the link from uav2's router is
subject "uav2", so it admits only falconry/uav2/** publications from it, i.e. what uav2's own
services send, and drops anything else that router forwards (a forged falconry/uav1/command,
but also, as a limitation, a third UAV's data relayed through uav2 when the direct link is
down, and the publications of a ground tool connected to uav2's router for another UAV).
Everything is checked at the first router a message enters and again at every router hop.

Limitations: the ACL is enforced by routers only. In the embedded profile (`falconry sim
--tls` without `--zenoh-profile router`) every process is a peer and links peer to peer: TLS
then authenticates and encrypts (only holders of a team certificate connect) but no
per-identity access control applies. Queries are admitted on falconry/** for every member,
so a queryable must not act on a query (ours only answer: health, resume).

Its functions are pure (no Zenoh, no files): they compute names, paths and configuration values.
Only `main`, `python -m services.lib.runtime.tls write-deploy-configs`, writes files: the checked-in
zenohd configs.
"""
from __future__ import annotations

import ipaddress
import json
import sys
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from schemas import keys

SIM = keys.SIM
GROUND = "ground"
ROUTER = "router"
ROLES = (SIM, GROUND, ROUTER)  # the identities besides the UAVs
CA = "ca"
ENV_DIR = "FALCONRY_TLS_DIR"
ZENOH_PORT = 7447
RADIO_SUFFIX = ".radio"  # uavN.radio: a UAV's address on the radio link (/etc/hosts onboard)
COMPOSE_ROUTER_HOST = "zenoh"  # the router's service name in compose.yaml
DEPLOY_TLS_DIR = "/etc/falconry/tls"  # where the deploy configs expect the certificates
DEPLOY_TEAM = ("uav1", "uav2", "uav3")

# Zenoh's ACL message kinds, split by what they do to a key.
PUBLISH = ("put", "delete", "liveliness_token", "declare_queryable", "reply")  # speak for the key
ASK = ("declare_subscriber", "declare_liveliness_subscriber", "query", "liveliness_query")  # listen/ask

# The onboard router's link settings (deploy/zenoh/onboard-router.json5 has the same; a test
# holds them equal): a cut radio link shows after 3 s, a partner back in range is reconnected
# within about 4 s.
ONBOARD_LEASE_MS = 3000
KEEP_ALIVE = 4  # keep-alives per lease, with any --lease-ms (zenoh_config too)
ROUTER_RETRY = {"period_init_ms": 500, "period_max_ms": 4000, "period_increase_factor": 2}


class TlsError(ValueError):
    """A wrong identity or team name (callers turn it into their usage error)."""


@dataclass(frozen=True)
class TlsFiles:
    """The files one identity opens: the team's CA and its own certificate and key."""

    ca: Path
    certificate: Path
    private_key: Path

    def all(self) -> tuple[Path, Path, Path]:
        return self.ca, self.certificate, self.private_key


def check_team(uavs) -> list[str]:
    """A team: distinct valid UAV names, none of them a role's name."""
    team = list(uavs)
    if not team:
        raise TlsError("a team needs at least one UAV")
    for uav in team:
        try:
            keys.check_name(uav, "UAV name")
        except ValueError as exc:
            raise TlsError(str(exc)) from None
        if uav in ROLES or uav == CA:
            raise TlsError(f"a UAV cannot be named {uav!r}: that is the name of an identity or of the CA")
    if len(set(team)) != len(team):
        raise TlsError(f"the team names a UAV twice: {','.join(team)}")
    return team


def parse_team(text: str) -> list[str]:
    """`--team uav1,uav2` → ["uav1", "uav2"]."""
    return check_team([name.strip() for name in text.split(",") if name.strip()])


def identities(team) -> list[str]:
    """Every identity of a team, in the order certificates are made: the UAVs, then the roles."""
    return check_team(team) + list(ROLES)


def check_identity(name: str) -> str:
    if name in ROLES:
        return name
    try:
        if name == CA:
            raise ValueError(name)
        return keys.check_name(name, "TLS identity")
    except ValueError:
        raise TlsError(f"invalid TLS identity {name!r}: a UAV name (e.g. uav1) or one of "
                       f"{', '.join(ROLES)}") from None


def identity_for(service: str | None, uav: str | None) -> str:
    """The identity a process authenticates as: a per-UAV service its UAV's, the simulator
    "sim", anything else (the ground tools: no service) "ground"."""
    if service is None:
        return GROUND
    if service in keys.SIM_SERVICES:
        return SIM
    if not uav:
        raise TlsError(f"{service} is a per-UAV service: its TLS identity is its UAV's (give --uav)")
    return check_identity(uav)


def files(directory: str | Path, identity: str) -> TlsFiles:
    base = Path(directory)
    return TlsFiles(ca=base / f"{CA}.crt", certificate=base / f"{identity}.crt", private_key=base / f"{identity}.key")


def ca_key(directory: str | Path) -> Path:
    return Path(directory) / f"{CA}.key"


def radio_host(uav: str) -> str:
    return uav + RADIO_SUFFIX


def host_names(identity: str, extra_hosts=()) -> tuple[list[str], list[str]]:
    """(DNS names, IP addresses) a certificate of `identity` is valid for: its own name,
    uavN.radio for a UAV (its onboard router on the radio), the compose service name for the
    router, localhost and 127.0.0.1 (a UAV's services reach their router on loopback), plus
    `extra_hosts` (names or addresses)."""
    dns = [identity]
    if identity not in ROLES:
        dns.append(radio_host(identity))
    if identity == ROUTER:
        dns.append(COMPOSE_ROUTER_HOST)
    dns.append("localhost")
    ips = ["127.0.0.1"]
    for host in extra_hosts:
        try:
            address = str(ipaddress.ip_address(host))
        except ValueError:
            if not host or any(c.isspace() or c in "/:" for c in host):
                raise TlsError(f"invalid host name {host!r}") from None
            if host not in dns:
                dns.append(host)
        else:
            if address not in ips:
                ips.append(address)
    return dns, ips


def endpoint_is_tls(endpoint: str) -> bool:
    return endpoint.partition("/")[0] == "tls"


# ------------------------------------------------------------ zenoh configuration values
def tls_settings(tls_files: TlsFiles) -> dict[str, object]:
    """transport/link/tls for mutual TLS: trust only the team CA, present this identity's
    certificate whether listening or connecting, require one from the other side, and check
    the server's name against its certificate."""
    return {
        "root_ca_certificate": str(tls_files.ca),
        "listen_certificate": str(tls_files.certificate),
        "listen_private_key": str(tls_files.private_key),
        "connect_certificate": str(tls_files.certificate),
        "connect_private_key": str(tls_files.private_key),
        "enable_mtls": True,
        "verify_name_on_connect": True,
    }


def session_inserts(tls_files: TlsFiles) -> dict[str, object]:
    """Config inserts (path → value) for a client or peer with mutual TLS."""
    return {f"transport/link/tls/{name}": value for name, value in tls_settings(tls_files).items()}


def access_control(team) -> dict[str, object]:
    """The team's `access_control` block (see the module's doc for what each identity may do)."""
    team = check_team(team)
    everything = [f"{keys.ROOT}/**"]
    rules: list[dict[str, object]] = [
        {"id": "receive", "messages": list(PUBLISH + ASK), "flows": ["egress"], "permission": "allow",
         "key_exprs": everything},
        {"id": "ask", "messages": list(ASK), "flows": ["ingress"], "permission": "allow", "key_exprs": everything},
    ]
    publishes = {uav: [keys.uav(uav, "**")] for uav in team}
    flight_controllers = [keys.uav(uav, topic) for uav in team for topic in keys.FLIGHT_CONTROLLER_TOPICS]
    publishes[SIM] = [keys.sim("**")] + flight_controllers
    publishes[GROUND] = [keys.uav(uav, keys.COLORS) for uav in team]
    subjects, policies = [], []
    for identity, key_exprs in publishes.items():
        rules.append({"id": f"publish-{identity}", "messages": list(PUBLISH), "flows": ["ingress"],
                      "permission": "allow", "key_exprs": key_exprs})
        subjects.append({"id": identity, "cert_common_names": [identity]})
        policies.append({"id": identity, "rules": ["receive", "ask", f"publish-{identity}"], "subjects": [identity]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_inserts(listen, connect=(), lease_ms: int | None = None, tls_files: TlsFiles | None = None,
                   team=None) -> dict[str, object]:
    """Config inserts (path → value) of a Falconry router: multicast scouting off (routers meet
    through explicit endpoints), `connect` retried for ever and never fatal (a partner out of
    range), the lease, and with `tls_files` mutual TLS and the team's access control (which
    needs the certificates: team and tls_files go together)."""
    if (tls_files is None) != (team is None):
        raise TlsError("the team's access control identifies parties by their certificates: "
                       "give both the TLS files and the team")
    inserts: dict[str, object] = {
        "mode": "router",
        "listen/endpoints": list(listen),
    }
    if connect:
        inserts.update({
            "connect/endpoints": list(connect),
            "connect/timeout_ms": {"router": -1, "peer": -1, "client": 0},
            "connect/exit_on_failure": {"router": False, "peer": False, "client": True},
            "connect/retry": dict(ROUTER_RETRY),
        })
    inserts.update({"scouting/multicast/enabled": False, "scouting/gossip/enabled": True})
    if lease_ms:
        inserts.update({"transport/link/tx/lease": lease_ms, "transport/link/tx/keep_alive": KEEP_ALIVE})
    if tls_files is not None:
        inserts.update({f"transport/link/tls/{k}": v for k, v in tls_settings(tls_files).items()})
        inserts["access_control"] = access_control(team)
    return inserts


def nest(inserts: dict[str, object]) -> dict[str, object]:
    """Config inserts as the nested object a JSON5 config file holds."""
    config: dict[str, object] = {}
    for path, value in inserts.items():
        *parents, leaf = path.split("/")
        node = config
        for part in parents:
            node = node.setdefault(part, {})  # type: ignore[assignment]
        node[leaf] = value
    return config


# ------------------------------------------------------------------- deploy configs
GENERATED_BY = "python -m services.lib.runtime.tls write-deploy-configs"
COMPOSE_CONFIG = "deploy/zenoh/router-tls.json5"


def onboard_config_path(uav: str) -> str:
    return f"deploy/onboard/{uav}/router.json5"


def _deploy_files(identity: str) -> TlsFiles:
    base = PurePosixPath(DEPLOY_TLS_DIR)
    return TlsFiles(ca=Path(base / f"{CA}.crt"), certificate=Path(base / f"{identity}.crt"),
                    private_key=Path(base / f"{identity}.key"))


def _json5(value: object, indent: str = "") -> str:
    """JSON5 in the style of the hand-written configs: bare keys, trailing commas, a list of
    plain values on one line."""
    inner = indent + "  "
    if isinstance(value, dict) and value and not any(isinstance(v, dict) for v in value.values()) \
            and not any(isinstance(x, (dict, list)) for v in value.values() if isinstance(v, list) for x in v):
        line = "{ " + ", ".join(f"{k}: {_json5(v)}" for k, v in value.items()) + " }"
        if len(indent) + len(line) <= 96:
            return line
    if isinstance(value, dict):
        return "{\n" + "".join(f"{inner}{k}: {_json5(v, inner)},\n" for k, v in value.items()) + indent + "}"
    if isinstance(value, list) and any(isinstance(v, (dict, list)) for v in value):
        return "[\n" + "".join(f"{inner}{_json5(v, inner)},\n" for v in value) + indent + "]"
    return json.dumps(value, separators=(", ", ": "))


def _render(header: str, config: dict[str, object]) -> str:
    lines = [f"// {line}" if line else "//" for line in header.strip("\n").splitlines()]
    return "\n".join(lines) + "\n" + _json5(config) + "\n"


def compose_router_config(team=DEPLOY_TEAM) -> str:
    listen = f"tls/0.0.0.0:{ZENOH_PORT}"
    header = f"""\
GENERATED by `{GENERATED_BY}` (services/lib/runtime/tls.py); do not edit:
change the generator and run it again (tests/test_tls.py checks this file is its output).

The compose router with mutual TLS and the access control of team {','.join(team)}
(+ sim, ground). Every party presents a certificate of the team CA; see deploy/README.md,
"Security: mutual TLS and access control". Certificates: `falconry certs DIR
--team {','.join(team)}`, DIR mounted at {DEPLOY_TLS_DIR} (this router uses {ROUTER}.crt/.key).
Services connect with
  falconry run SERVICE --uav uavN --zenoh-profile router --connect tls/{COMPOSE_ROUTER_HOST}:{ZENOH_PORT} --tls {DEPLOY_TLS_DIR}
Each UAV may publish only under falconry/<its uav>/**, sim only falconry/sim/** and each
UAV's odometry and imu, ground only each UAV's colors; everyone may read falconry/**."""
    return _render(header, nest(router_inserts([listen], tls_files=_deploy_files(ROUTER), team=list(team))))


def onboard_router_config(uav: str, team=DEPLOY_TEAM) -> str:
    team = check_team(team)
    if uav not in team:
        raise TlsError(f"{uav} is not in the team {','.join(team)}")
    partners = [u for u in team if u != uav]
    connect = [f"tls/{radio_host(u)}:{ZENOH_PORT}" for u in partners]
    header = f"""\
GENERATED by `{GENERATED_BY}` (services/lib/runtime/tls.py); do not edit:
change the generator and run it again (tests/test_tls.py checks this file is its output).

{uav}'s onboard router with mutual TLS (deploy/zenoh/onboard-router.json5 is the plain one):
it listens on tls/0.0.0.0:{ZENOH_PORT} for {uav}'s services (loopback) and the partners' routers
(radio), and connects to the partners {', '.join(connect)}
(map uavN{RADIO_SUFFIX} to the radio addresses in /etc/hosts; a partner out of range is retried, never
fatal). It authenticates as {uav} ({DEPLOY_TLS_DIR}/{uav}.crt/.key) and enforces the team's access
control: a partner's router is admitted only for that partner's own keys (falconry/<partner>/**).
{uav}'s services: falconry run SERVICE --uav {uav} --clock wall --zenoh-profile router
  --connect tls/127.0.0.1:{ZENOH_PORT} --tls {DEPLOY_TLS_DIR}
or: falconry router --listen tls/0.0.0.0:{ZENOH_PORT} {' '.join('--connect ' + c for c in connect)}
  --lease-ms {ONBOARD_LEASE_MS} --tls {DEPLOY_TLS_DIR} --tls-identity {uav} --team {','.join(team)}"""
    inserts = router_inserts([f"tls/0.0.0.0:{ZENOH_PORT}"], connect, ONBOARD_LEASE_MS, _deploy_files(uav), team)
    return _render(header, nest(inserts))


def deploy_configs(team=DEPLOY_TEAM) -> dict[str, str]:
    """Every checked-in TLS router config: repository-relative path → text."""
    configs = {COMPOSE_CONFIG: compose_router_config(team)}
    configs.update({onboard_config_path(uav): onboard_router_config(uav, team) for uav in team})
    return configs


def main(argv: list[str] | None = None) -> int:
    """`python -m services.lib.runtime.tls write-deploy-configs [--check]` (from the repository root)."""
    args = sys.argv[1:] if argv is None else argv
    if not args or args[0] != "write-deploy-configs" or args[1:] not in ([], ["--check"]):
        print("usage: python -m services.lib.runtime.tls write-deploy-configs [--check]", file=sys.stderr)
        return 2
    root = Path(__file__).resolve().parents[3]
    stale = []
    for relative, text in deploy_configs().items():
        path = root / relative
        if args[1:] == ["--check"]:
            if not path.is_file() or path.read_text() != text:
                stale.append(relative)
            continue
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        print(f"wrote {relative}")
    for relative in stale:
        print(f"{relative} differs from the generator's output", file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
