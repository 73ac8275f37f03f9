"""Who may do what on the bus, with Zenoh's own security (docs/operations.md, "Secured mode").

Everything here is configuration for the Zenoh router opened by the eclipse-zenoh
wheel; the services and vehicles only load a client config file:

- **transport**: TLS on every link (``tls/HOST:PORT``), the router's certificate
  signed by the deployment CA;
- **authentication**: ``mtls`` (the production option: one client certificate per
  vehicle and per service, the identity is the certificate's common name) or
  ``usrpwd`` (user/password checked against the router's dictionary file, the
  identity is the user name; TLS still encrypts and authenticates the router);
- **authorization**: an ACL on the router, default deny. Services (and the
  ``operator`` identity of ``hdmap status``) may do everything under ``hdmap/v1/**``.
  A vehicle may only query ``hdmap/v1/upload/<its own id>`` and
  ``hdmap/v1/map/<tile>/by/<its own id>`` (snapshots asked for under its authenticated
  id, which the publisher limits per client), subscribe to ``hdmap/v1/map/*/delta``, and
  receive the matching samples and replies: no anonymous snapshot query
  (``hdmap/v1/map/<tile>``, which all share one budget), no put, no delete, no other
  subscription, no queryable, no liveliness.

Measured with eclipse-zenoh 1.10.2 (tests/test_security.py shows each over real
connections): a denied put or delete returns normally and is dropped at the router;
a denied query returns at once with no reply; a denied subscription or queryable is
declared without error and never receives anything; receiving needs the *egress*
side allowed too (``put``/``reply`` toward the vehicle); a client whose certificate
or password is missing or wrong cannot open a session (``zenoh.open`` raises
``ZError`` at once); a subject listing both ``cert_common_names`` and ``usernames``
requires both (AND). Queries, subscriptions and tokens that a session matches itself
are served locally, without the router: a test must use separate sessions.

**Scaling limit.** Zenoh's ACL has no "the caller's own name" placeholder, so the
rights on a vehicle's own keys take one rule, one subject and one policy per vehicle
(~340 bytes of config). A 20,000-vehicle ACL (measured with the upload key alone, ~280
bytes each) loaded and opened in ~2.5 s and did not slow a vehicle's connect (31 ms) or
its uploads; but the ACL is read once at router start, so adding or revoking a vehicle
means regenerating the router config from the vehicle registry and restarting the router
(clients reconnect). Shard vehicles over several routers by region when the file or
restarts become a burden.
"""

from __future__ import annotations

import argparse
import datetime
import ipaddress
import json
import os
import re
import secrets
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from hdmap.runtime.bus import BusConfig
from schemas import keys

SERVICE_IDENTITIES = ("ingest", "matcher", "solver", "publisher", "operator")
"""Identities with every right under ``hdmap/v1/**`` (``operator``: ``hdmap status``)."""
OPERATOR = "operator"
AUTH_MODES = ("mtls", "usrpwd")
ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
IDENTITY_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")
"""One key chunk, a user name (no ':') and a file name: no '/', '*', '$', '?', '#', ':'."""


def check_identity(name: str) -> str:
    if not IDENTITY_RE.match(name):
        raise ValueError(
            f"{name!r}: an identity is 1-64 of [A-Za-z0-9._-], not starting with . _ -"
        )
    return name


def tls_endpoint(endpoint: str) -> str:
    """'tcp/127.0.0.1:7447' -> 'tls/127.0.0.1:7447' (secure mode listens on TLS only)."""
    proto, _, rest = endpoint.partition("/")
    return endpoint if proto == "tls" else f"tls/{rest}"


# -- ACL --------------------------------------------------------------------------------------


def acl(services: Sequence[str], vehicles: Sequence[str], auth: str = "mtls") -> dict[str, Any]:
    """The router's ``access_control`` section (default deny).

    >>> a = acl(["ingest"], ["veh-1", "veh-2"])
    >>> len(a["rules"]), len(a["subjects"]), len(a["policies"])
    (7, 4, 4)
    >>> [r["key_exprs"] for r in a["rules"] if r["id"] == "own-veh-2"]
    [['hdmap/v1/upload/veh-2', 'hdmap/v1/map/*/by/veh-2']]
    """
    if auth not in AUTH_MODES:
        raise ValueError(f"auth {auth!r}: one of {AUTH_MODES}")
    field = "cert_common_names" if auth == "mtls" else "usernames"
    for name in (*services, *vehicles):
        check_identity(name)
    if set(services) & set(vehicles):
        raise ValueError(f"identities both service and vehicle: {set(services) & set(vehicles)}")

    def rule(rid: str, messages: list[str], flow: str | list[str], key_exprs: list[str]) -> dict:
        flows = [flow] if isinstance(flow, str) else flow
        return {
            "id": rid,
            "messages": messages,
            "flows": flows,
            "permission": "allow",
            "key_exprs": key_exprs,
        }

    delta, snap = keys.map_delta(keys.ANY), keys.map_snapshot_for(keys.ANY, keys.ANY)
    rules = [rule("services-all", list(ALL_MESSAGES), ["ingress", "egress"], [f"{keys.ROOT}/**"])]
    # A subject without names matches anyone (an empty list is refused by Zenoh): none here.
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    if services:
        subjects.append({"id": "services", field: list(services)})
        policies.append({"id": "services", "rules": ["services-all"], "subjects": ["services"]})
    if vehicles:
        rules += [
            rule("vehicle-subscribe-deltas", ["declare_subscriber"], "ingress", [delta]),
            rule("vehicle-receive-deltas", ["put"], "egress", [delta]),
            # A vehicle only gets replies to its own queries: shared reply rules are enough.
            rule("vehicle-receive-snapshots", ["reply"], "egress", [snap]),
            rule("vehicle-receive-upload-acks", ["reply"], "egress", [keys.upload(keys.ANY)]),
        ]
        subjects.append({"id": "vehicles", field: list(vehicles)})
        shared = [r["id"] for r in rules if r["id"].startswith("vehicle-")]
        policies.append({"id": "vehicles", "rules": shared, "subjects": ["vehicles"]})
    for v in vehicles:  # the scaling limit: one rule + subject + policy per vehicle
        # Its own keys only: it uploads as itself, and asks for snapshots as itself (the
        # publisher's per-client limit then holds for its authenticated id).
        own = [keys.upload(v), keys.map_snapshot_for(v, keys.ANY)]
        rules.append(rule(f"own-{v}", ["query"], "ingress", own))
        subjects.append({"id": f"vehicle-{v}", field: [v]})
        policies.append({"id": f"vehicle-{v}", "rules": [f"own-{v}"], "subjects": [f"vehicle-{v}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


# -- PKI --------------------------------------------------------------------------------------


def _now() -> datetime.datetime:
    return datetime.datetime.now(datetime.UTC)


def _write_private(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    _write_private(
        path,
        key.private_bytes(
            serialization.Encoding.PEM,
            serialization.PrivateFormat.PKCS8,
            serialization.NoEncryption(),
        ),
    )


def _key_usage(ca: bool) -> x509.KeyUsage:
    return x509.KeyUsage(
        digital_signature=True,
        content_commitment=False,
        key_encipherment=False,
        data_encipherment=False,
        key_agreement=False,
        key_cert_sign=ca,
        crl_sign=ca,
        encipher_only=False,
        decipher_only=False,
    )


def create_ca(out_dir: Path, name: str = "hdmap test CA", days: int = 30) -> tuple[Path, Path]:
    """A self-signed CA: (ca.pem, ca.key) in ``out_dir``."""
    out_dir.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(subject)
        .issuer_name(subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_now() - datetime.timedelta(minutes=5))
        .not_valid_after(_now() + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(_key_usage(ca=True), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    cert_path, key_path = out_dir / "ca.pem", out_dir / "ca.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, key_path)
    return cert_path, key_path


def issue_certificate(
    ca_cert: Path,
    ca_key: Path,
    common_name: str,
    out_dir: Path,
    server_hosts: Iterable[str] = (),
    days: int = 30,
) -> tuple[Path, Path]:
    """A certificate signed by the CA: (<cn>.pem, <cn>.key) in ``out_dir``.

    With ``server_hosts`` it is a TLS server certificate valid for those IPs/names
    (the router); without, a client certificate whose common name is the identity
    the router's ACL matches (``cert_common_names``).
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    ca = x509.load_pem_x509_certificate(ca_cert.read_bytes())
    signer = serialization.load_pem_private_key(ca_key.read_bytes(), None)
    assert isinstance(signer, ec.EllipticCurvePrivateKey)
    key = ec.generate_private_key(ec.SECP256R1())
    hosts = list(server_hosts)
    usage = ExtendedKeyUsageOID.SERVER_AUTH if hosts else ExtendedKeyUsageOID.CLIENT_AUTH
    builder = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(ca.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(_now() - datetime.timedelta(minutes=5))
        .not_valid_after(_now() + datetime.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(_key_usage(ca=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([usage]), critical=False)
        .add_extension(
            x509.AuthorityKeyIdentifier.from_issuer_public_key(signer.public_key()), critical=False
        )
    )
    if hosts:
        names: list[x509.GeneralName] = []
        for h in dict.fromkeys(hosts):
            try:
                names.append(x509.IPAddress(ipaddress.ip_address(h)))
            except ValueError:
                names.append(x509.DNSName(h))
        builder = builder.add_extension(x509.SubjectAlternativeName(names), critical=False)
    cert = builder.sign(signer, hashes.SHA256())
    cert_path, key_path = out_dir / f"{common_name}.pem", out_dir / f"{common_name}.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, key_path)
    return cert_path, key_path


# -- deployment -------------------------------------------------------------------------------


@dataclass(frozen=True)
class SecureDeployment:
    """The files of one secured deployment (see :func:`generate`)."""

    root: Path
    auth: str
    endpoint: str
    services: tuple[str, ...]
    vehicles: tuple[str, ...]

    @property
    def pki(self) -> Path:
        return self.root / "pki"

    @property
    def router_config(self) -> Path:
        return self.root / "router.json5"

    @property
    def users_file(self) -> Path:
        return self.root / "users.txt"

    def service_config(self, name: str) -> Path:
        return self.root / f"service-{name}.json5"

    def vehicle_config(self, vehicle_id: str) -> Path:
        return self.root / f"vehicle-{vehicle_id}.json5"

    def client_config(self, identity: str) -> Path:
        if identity in self.services:
            return self.service_config(identity)
        if identity in self.vehicles:
            return self.vehicle_config(identity)
        raise KeyError(f"{identity!r} is neither a service nor a vehicle of this deployment")

    def bus(self, identity: str) -> BusConfig:
        return BusConfig(
            mode="client", connect=(self.endpoint,), config_file=str(self.client_config(identity))
        )


def _write_json5(path: Path, header: str, conf: dict[str, Any], private: bool = False) -> None:
    text = "".join(f"// {line}\n" for line in header.splitlines()) + json.dumps(conf, indent=2)
    if private:
        _write_private(path, (text + "\n").encode())
    else:
        path.write_text(text + "\n")


def router_conf(dep: SecureDeployment) -> dict[str, Any]:
    tls: dict[str, Any] = {
        "root_ca_certificate": str(dep.pki / "ca.pem"),
        "listen_private_key": str(dep.pki / "router.key"),
        "listen_certificate": str(dep.pki / "router.pem"),
        "enable_mtls": dep.auth == "mtls",
    }
    transport: dict[str, Any] = {"link": {"protocols": ["tls"], "tls": tls}}
    if dep.auth == "usrpwd":
        transport["auth"] = {"usrpwd": {"dictionary_file": str(dep.users_file)}}
    return {
        "mode": "router",
        "listen": {"endpoints": [dep.endpoint]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": transport,
        "access_control": acl(dep.services, dep.vehicles, dep.auth),
    }


def client_conf(dep: SecureDeployment, identity: str, password: str | None) -> dict[str, Any]:
    tls: dict[str, Any] = {"root_ca_certificate": str(dep.pki / "ca.pem")}
    if dep.auth == "mtls":
        tls.update(
            connect_private_key=str(dep.pki / f"{identity}.key"),
            connect_certificate=str(dep.pki / f"{identity}.pem"),
            enable_mtls=True,
        )
    transport: dict[str, Any] = {"link": {"tls": tls}}
    if password is not None:
        transport["auth"] = {"usrpwd": {"user": identity, "password": password}}
    return {
        "mode": "client",
        "connect": {"endpoints": [dep.endpoint]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": transport,
    }


def generate(
    root: Path,
    vehicles: Sequence[str],
    endpoint: str,
    auth: str = "mtls",
    services: Sequence[str] = SERVICE_IDENTITIES,
    hosts: Iterable[str] = ("127.0.0.1", "localhost"),
    days: int = 30,
) -> SecureDeployment:
    """A test PKI, users dictionary and Zenoh configs for one deployment, under ``root``.

    Everything is regenerated (a new CA each time): fine for tests and ``hdmap up
    --secure``; a production deployment keeps its CA offline and generates only the
    router config from its vehicle registry (deploy/secure/README.md).
    """
    if auth not in AUTH_MODES:
        raise ValueError(f"auth {auth!r}: one of {AUTH_MODES}")
    endpoint = tls_endpoint(endpoint)
    dep = SecureDeployment(Path(root), auth, endpoint, tuple(services), tuple(vehicles))
    acl(dep.services, dep.vehicles, auth)  # validates the identities
    dep.root.mkdir(parents=True, exist_ok=True)
    ca_cert, ca_key = create_ca(dep.pki, days=days)
    host = endpoint.split("/", 1)[1].rsplit(":", 1)[0].strip("[]")
    server_hosts = [*hosts, *([host] if host not in ("0.0.0.0", "::") else [])]
    issue_certificate(ca_cert, ca_key, "router", dep.pki, server_hosts, days)
    passwords: dict[str, str | None] = {}
    for identity in (*dep.services, *dep.vehicles):
        if auth == "mtls":
            issue_certificate(ca_cert, ca_key, identity, dep.pki, days=days)
            passwords[identity] = None
        else:
            passwords[identity] = secrets.token_urlsafe(18)
    if auth == "usrpwd":
        _write_private(dep.users_file, "".join(f"{u}:{p}\n" for u, p in passwords.items()).encode())
    _write_json5(
        dep.router_config,
        f"hdmap router, {auth}, {len(dep.vehicles)} vehicles (generated by hdmap.ops.security)",
        router_conf(dep),
    )
    for identity, password in passwords.items():
        kind = "service" if identity in dep.services else "vehicle"
        _write_json5(
            dep.client_config(identity),
            f"hdmap {kind} {identity!r}, {auth} (generated by hdmap.ops.security)",
            client_conf(dep, identity, password),
            private=password is not None,
        )
    return dep


def main(argv: list[str] | None = None) -> int:
    """``python -m hdmap.ops.security``: generate a deployment or issue one certificate."""
    p = argparse.ArgumentParser(prog="python -m hdmap.ops.security", description=main.__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    g = sub.add_parser("generate", help="test PKI + router/service/vehicle configs")
    g.add_argument("--out", required=True, type=Path)
    g.add_argument("--endpoint", default="tls/127.0.0.1:7447")
    g.add_argument("--auth", choices=AUTH_MODES, default="mtls")
    g.add_argument("--vehicle", action="append", default=[], metavar="ID")
    g.add_argument("--host", action="append", default=[], help="extra router cert name/IP")
    i = sub.add_parser("issue", help="a client certificate signed by an existing CA")
    i.add_argument("--ca-dir", required=True, type=Path, help="holds ca.pem and ca.key")
    i.add_argument("--cn", required=True, help="vehicle or service id (the ACL identity)")
    i.add_argument("--out", required=True, type=Path)
    i.add_argument("--days", type=int, default=30)
    args = p.parse_args(argv)
    if args.cmd == "generate":
        dep = generate(
            args.out,
            args.vehicle,
            args.endpoint,
            args.auth,
            hosts=["127.0.0.1", "localhost", *args.host],
        )
        print(f"router config: {dep.router_config}")
        for v in dep.vehicles:
            print(f"vehicle {v}: {dep.vehicle_config(v)}")
    else:
        cert, key = issue_certificate(
            args.ca_dir / "ca.pem",
            args.ca_dir / "ca.key",
            check_identity(args.cn),
            args.out,
            days=args.days,
        )
        print(f"{cert}\n{key}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
