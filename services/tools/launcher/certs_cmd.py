"""`falconry certs DIR`: a test CA and a certificate per identity of a team, for mutual TLS.

The identities and what each may publish are services/lib/runtime/tls.py's; this command only makes
the keys and certificates (EC P-256, signed by the CA) with the `cryptography` library."""
from __future__ import annotations

import argparse
import datetime
import ipaddress
import os
from pathlib import Path

from services.lib.runtime import tls
from services.tools.launcher.common import CliError, add_team_options, team_of

DEFAULT_UAVS = 3
DEFAULT_DAYS = 365
# Certificates start being valid this long before they are made: a machine whose clock is a
# little behind the signer's must not see them as not yet valid.
BACKDATE = datetime.timedelta(hours=1)


def add_parser(commands) -> None:
    p = commands.add_parser(
        "certs", help="make a test CA and a TLS certificate per identity of a team",
        description="Write into DIR a test certificate authority (ca.crt, ca.key) and, for every identity of the "
                    "team (each UAV, sim, ground, router), IDENTITY.crt and IDENTITY.key signed by it, with the "
                    "identity as common name: the router's access control tells parties apart by it. Each "
                    "certificate is valid for the names IDENTITY, localhost and 127.0.0.1, plus uavN.radio for a "
                    "UAV and zenoh (the compose router) for the router, plus every --host. Keys are written "
                    "readable by their owner only. Then start the router and the services with --tls DIR "
                    "(deploy/README.md, \"Security\"). A UAV needs only ca.crt and its own pair; ca.key signs "
                    "certificates: keep it off the UAVs.")
    p.add_argument("dir", metavar="DIR", help="directory to write into (created if missing)")
    add_team_options(p, "the team's UAVs", default=DEFAULT_UAVS)
    p.add_argument("--days", type=int, default=DEFAULT_DAYS, metavar="D",
                   help=f"validity of the CA and every certificate, in days (default {DEFAULT_DAYS})")
    p.add_argument("--host", action="append", default=[], metavar="NAME",
                   help="another DNS name or IP address every certificate is valid for, e.g. a radio address "
                        "(repeatable)")
    p.add_argument("--force", action="store_true",
                   help="replace an existing CA in DIR (and so every certificate: the old ones stop being trusted)")
    p.set_defaults(handler=run_certs)


MAX_DAYS = 36_500  # 100 years: X.509 validity dates cannot go past 9999


def run_certs(args: argparse.Namespace) -> int:
    team = team_of(args, default=DEFAULT_UAVS)
    if not 1 <= args.days <= MAX_DAYS:
        raise CliError(f"--days must be from 1 to {MAX_DAYS} (X.509 dates end in 9999), not {args.days}")
    directory = Path(args.dir)
    try:
        hosts = {identity: tls.host_names(identity, args.host) for identity in tls.identities(team)}
    except tls.TlsError as exc:
        raise CliError(f"--host: {exc}") from None
    if directory.exists() and not directory.is_dir():
        raise CliError(f"{directory} exists and is not a directory")
    existing = [p for p in (tls.files(directory, tls.CA).certificate, tls.ca_key(directory)) if p.exists()]
    if existing and not args.force:
        raise CliError(f"{existing[0]} exists: a new CA would invalidate every certificate it signed "
                       f"(give --force to replace it, or another DIR)")
    try:
        directory.mkdir(parents=True, exist_ok=True)
        written = write_team(directory, hosts, args.days)
    except OSError as exc:
        raise CliError(f"cannot write into {directory}: {exc.strerror or exc}") from None
    print(f"wrote into {directory} (valid {args.days} days):")
    for line in written:
        print(f"  {line}")
    team_arg = ",".join(team)
    print(f"""next:
  router:   falconry router --listen tls/0.0.0.0:{tls.ZENOH_PORT} --tls {directory} --team {team_arg}
            (or zenohd with deploy/zenoh/router-tls.json5 and {directory} at {tls.DEPLOY_TLS_DIR})
  services: falconry run SERVICE --uav UAV --zenoh-profile router --connect tls/HOST:{tls.ZENOH_PORT} --tls {directory}
            (or FALCONRY_TLS_DIR={directory}); ground tools the same way, as 'ground'
  onboard:  copy ca.crt and that UAV's UAV.crt/UAV.key only; keep ca.key off the UAVs""")
    return 0


def write_team(directory: Path, hosts: dict[str, tuple[list[str], list[str]]], days: int) -> list[str]:
    """The CA and a certificate per identity (`hosts`: identity → (DNS names, IP addresses));
    one line per file pair written."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = datetime.datetime.now(datetime.timezone.utc)
    start, end = now - BACKDATE, now + datetime.timedelta(days=days)

    def write_key(path: Path, key) -> None:
        data = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                 serialization.NoEncryption())
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        try:
            os.fchmod(fd, 0o600)  # an existing file keeps its mode through O_CREAT
            os.write(fd, data)
        finally:
            os.close(fd)

    def write_cert(path: Path, cert) -> None:
        path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        os.chmod(path, 0o644)

    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_name = x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "Falconry"),
                         x509.NameAttribute(NameOID.COMMON_NAME, "Falconry test CA")])
    ca_cert = (x509.CertificateBuilder()
               .subject_name(ca_name).issuer_name(ca_name).public_key(ca_key.public_key())
               .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
               .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
               .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                            data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                            crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
               .add_extension(x509.SubjectKeyIdentifier.from_public_key(ca_key.public_key()), critical=False)
               .sign(ca_key, hashes.SHA256()))
    ca_files = tls.files(directory, tls.CA)
    write_key(tls.ca_key(directory), ca_key)
    write_cert(ca_files.certificate, ca_cert)
    lines = [f"{ca_files.certificate.name}, {tls.ca_key(directory).name}  the team's CA (ca.key signs: keep it safe)"]
    for identity, (dns, ips) in hosts.items():
        key = ec.generate_private_key(ec.SECP256R1())
        names = [x509.DNSName(name) for name in dns] + [x509.IPAddress(ipaddress.ip_address(ip)) for ip in ips]
        cert = (x509.CertificateBuilder()
                .subject_name(x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "Falconry"),
                                         x509.NameAttribute(NameOID.COMMON_NAME, identity)]))
                .issuer_name(ca_name).public_key(key.public_key())
                .serial_number(x509.random_serial_number()).not_valid_before(start).not_valid_after(end)
                .add_extension(x509.SubjectAlternativeName(names), critical=False)
                .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
                .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                             data_encipherment=False, key_agreement=True, key_cert_sign=False,
                                             crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
                # both: a UAV's router listens for its services and connects to its partners
                .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                      ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
                .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
                .sign(ca_key, hashes.SHA256()))
        files = tls.files(directory, identity)
        write_key(files.private_key, key)
        write_cert(files.certificate, cert)
        lines.append(f"{files.certificate.name}, {files.private_key.name}  CN {identity}; "
                     f"{', '.join(dns + ips)}")
    return lines
