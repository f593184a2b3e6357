"""A closed Zenoh bus: mutual TLS with a per-run certificate authority, and Zenoh's access control.

Why: a plain TCP bus lets any local (or routed) process join, read every key and publish on any of them
(issue 39). With mutual TLS only sessions holding a certificate of the run's CA connect; with the access
control list (ACL) each of those may publish only its own keys and receive only what it needs, keyed by
the certificate's common name (CN), never by the key expression it publishes on.

Roles and their CN: `world`, `coordinator`, `unit-<id>` (one per unit; a process hosting several units
uses the certificate of the unit whose link it opens first, and that CN is granted the keys of every unit
of the process), `router` (the session `sitl up --topology router` hosts: it forwards everything).

Files of a run directory (`RunCertificates.create`): `ca.crt`, `<role>.crt`, `<role>.key`, `acl.json`, and
`signing.key` (the per-run MAVLink signing key, when the user gave none); the directory is mode 0700, the
files 0600, and the directory is removed when the run ends (a copy is kept only with `--save-certs`).
"""

from __future__ import annotations

import datetime
import ipaddress
import json
import os
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROUTER_ROLE = "router"
CERT_VALIDITY_DAYS = 2  # a run's CA is thrown away at its end; two days cover any one run
ACL_FILE = "acl.json"
CA_FILE = "ca.crt"
SIGNING_KEY_FILE = "signing.key"  # 32 raw bytes: the per-run MAVLink signing key of the run's own links


def role_of_node(node: str) -> str:
    """The certificate role of a Zenoh node name ("world", "coordinator", "unit/<id>", "router")."""
    return node.replace("/", "-")


@dataclass(frozen=True)
class TlsFiles:
    """The PEM files one session uses: the CA that signs every peer, its own certificate and key."""

    ca: str
    cert: str
    key: str
    acl: str | None = None  # a JSON file with the `access_control` section, or None (mTLS only)


def _private_write(path: Path, data: bytes) -> None:
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)


def _name(common_name: str):
    from cryptography import x509
    from cryptography.x509.oid import NameOID

    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "mars-link run"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _certificate(subject: str, public_key, issuer: str, issuer_key, ca: bool):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes

    now = datetime.datetime.now(datetime.timezone.utc)
    builder = (x509.CertificateBuilder()
               .subject_name(_name(subject)).issuer_name(_name(issuer)).public_key(public_key)
               .serial_number(x509.random_serial_number())
               .not_valid_before(now - datetime.timedelta(minutes=5))
               .not_valid_after(now + datetime.timedelta(days=CERT_VALIDITY_DAYS))
               .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), critical=True))
    if ca:
        builder = builder.add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                                      content_commitment=False, key_encipherment=False,
                                                      data_encipherment=False, key_agreement=False,
                                                      encipher_only=False, decipher_only=False), critical=True)
    else:
        builder = builder.add_extension(x509.SubjectAlternativeName(
            [x509.DNSName("localhost"), x509.IPAddress(ipaddress.ip_address("127.0.0.1"))]), critical=False)
        builder = builder.add_extension(x509.ExtendedKeyUsage(
            [x509.oid.ExtendedKeyUsageOID.SERVER_AUTH, x509.oid.ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
    return builder.sign(issuer_key, hashes.SHA256())


def write_ca_and_certificates(directory: Path, roles: list[str], ca_name: str = "mars-link run CA") -> None:
    """A fresh CA (EC P-256) and one certificate + key per role, into `directory` (files 0600)."""
    from cryptography.hazmat.primitives import serialization
    from cryptography.hazmat.primitives.asymmetric import ec

    pem = serialization.Encoding.PEM
    ca_key = ec.generate_private_key(ec.SECP256R1())
    ca_cert = _certificate(ca_name, ca_key.public_key(), ca_name, ca_key, ca=True)
    _private_write(directory / CA_FILE, ca_cert.public_bytes(pem))
    for role in roles:
        key = ec.generate_private_key(ec.SECP256R1())
        cert = _certificate(role, key.public_key(), ca_name, ca_key, ca=False)
        _private_write(directory / f"{role}.crt", cert.public_bytes(pem))
        _private_write(directory / f"{role}.key", key.private_bytes(pem, serialization.PrivateFormat.PKCS8,
                                                                   serialization.NoEncryption()))


def access_control(fleet: str, unit_groups: list[list[int]], router: bool = False) -> dict:
    """Zenoh's `access_control` section for a run: default deny; each role may publish (`put` ingress at
    the others) only its own keys, receive (`put` egress towards it) and subscribe only to the keys meant
    for it. Subscriptions may be announced to any fleet member (egress `declare_subscriber`): that tells
    a publisher where to send, and the put rules still decide what it may send there. `router`: the run
    hosts a router session (it forwards everything; only then is its CN named at all)."""
    f = f"mars/{fleet}"
    # PX4's per-rotor interface (mars_link.px4, rmw_zenoh keys, domain 0): the coordinator writes each unit's
    # /px4_<id>/fmu/in/*, a unit its own /fmu/out/*; liveliness tokens (discovery only) are everyone's
    px4_in, px4_out = "0/px4_{}/fmu/in/**", "0/px4_{}/fmu/out/**"
    rules: list[dict] = [{"id": "announce", "messages": ["declare_subscriber"], "flows": ["egress"],
                          "permission": "allow", "key_exprs": [f"{f}/**", "0/px4_$*/fmu/**"]},
                         {"id": "discovery", "messages": ["liveliness_token", "declare_liveliness_subscriber",
                                                          "liveliness_query"],
                          "flows": ["ingress", "egress"], "permission": "allow", "key_exprs": ["@ros2_lv/**"]}]
    subjects: list[dict] = []
    policies: list[dict] = []
    if router:
        rules.append({"id": "router-all", "messages": ["put", "declare_subscriber"], "flows": ["ingress", "egress"],
                      "permission": "allow", "key_exprs": [f"{f}/**"]})
        subjects.append({"id": ROUTER_ROLE, "cert_common_names": [ROUTER_ROLE]})
        policies.append({"rules": ["router-all"], "subjects": [ROUTER_ROLE]})

    def role(name: str, cns: list[str], publishes: list[str], receives: list[str]) -> None:
        rules.append({"id": f"{name}-publish", "messages": ["put"], "flows": ["ingress"], "permission": "allow",
                      "key_exprs": publishes})
        rules.append({"id": f"{name}-receive", "messages": ["put"], "flows": ["egress"], "permission": "allow",
                      "key_exprs": receives})
        rules.append({"id": f"{name}-subscribe", "messages": ["declare_subscriber"], "flows": ["ingress"],
                      "permission": "allow", "key_exprs": receives})
        subjects.append({"id": name, "cert_common_names": cns})
        policies.append({"rules": ["announce", "discovery", f"{name}-publish", f"{name}-receive", f"{name}-subscribe"],
                         "subjects": [name]})

    role("world", ["world"], [f"{f}/unit/*/mavlink/down/world", f"{f}/*/mavlink/down/world"],
         [f"{f}/world/mavlink/down/*", f"{f}/unit/*/mavlink/up/world"])
    role("coordinator", ["coordinator"],
         [f"{f}/unit/*/mavlink/down/coordinator", f"{f}/*/mavlink/down/coordinator", px4_in.format("$*")],
         [f"{f}/coordinator/mavlink/down/*", f"{f}/unit/*/mavlink/up/coordinator", px4_out.format("$*")])
    for group in unit_groups:
        name = "units-" + "-".join(map(str, group))
        role(name, [f"unit-{u}" for u in group],
             [f"{f}/unit/{u}/mavlink/up/*" for u in group] + [px4_out.format(u) for u in group],
             [f"{f}/unit/{u}/mavlink/down/*" for u in group] + [px4_in.format(u) for u in group])
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


class RunCertificates:
    """A run's secrets in a private temporary directory (0700, files 0600), removed by `close`: the per-run
    CA, certificates and ACL of a closed bus, and/or the per-run MAVLink signing key of its own links."""

    def __init__(self, directory: Path, tls: bool = True) -> None:
        self.directory = directory
        self.tls = tls  # the directory holds the closed bus's CA, certificates and ACL

    @classmethod
    def create(cls, fleet: str, unit_groups: list[list[int]], tls: bool = True, signing_key: bool = False,
               router: bool = False) -> "RunCertificates":
        directory = Path(tempfile.mkdtemp(prefix="mars-link-run-"))  # mkdtemp: mode 0700
        try:
            if tls:
                roles = ["world", "coordinator"] + [ROUTER_ROLE] * router + [f"unit-{u}" for g in unit_groups for u in g]
                write_ca_and_certificates(directory, roles)
                _private_write(directory / ACL_FILE, json.dumps(access_control(fleet, unit_groups, router)).encode())
            if signing_key:
                _private_write(directory / SIGNING_KEY_FILE, os.urandom(32))  # (mars_link.mavlink.signing.load_key)
        except BaseException:
            shutil.rmtree(directory, ignore_errors=True)
            raise
        return cls(directory, tls)

    @property
    def signing_key_file(self) -> Path | None:
        path = self.directory / SIGNING_KEY_FILE
        return path if path.exists() else None

    def save(self, destination: Path) -> Path:
        """A copy into the run directory (`--save-certs`), still private: for a process of another host."""
        target = destination / "certs"
        target.mkdir(mode=0o700, parents=True, exist_ok=True)
        os.chmod(target, 0o700)
        for path in self.directory.iterdir():
            shutil.copy2(path, target / path.name)
            os.chmod(target / path.name, 0o600)
        return target

    def close(self) -> None:
        shutil.rmtree(self.directory, ignore_errors=True)


def files_for(tls_dir: str | None, ca: str | None, cert: str | None, key: str | None, node: str) -> TlsFiles | None:
    """The TLS files of node `node`'s session: the user's (`--tls-ca/--tls-cert/--tls-key`: mTLS, no ACL,
    every process of this host presents the same certificate), else the run's per-role ones, else None."""
    if ca or cert or key:
        return TlsFiles(ca or "", cert or "", key or "")
    if tls_dir is None:
        return None
    d = Path(tls_dir)
    role = role_of_node(node)
    return TlsFiles(str(d / CA_FILE), str(d / f"{role}.crt"), str(d / f"{role}.key"), str(d / ACL_FILE))


def check_user_files(ca: str | None, cert: str | None, key: str | None) -> str | None:
    """One line on what is wrong with the user's TLS options, or None."""
    given = [ca, cert, key]
    if not any(given):
        return None
    if not all(given):
        return "--tls-ca, --tls-cert and --tls-key go together (the CA of the fleet, this host's certificate and key)"
    for option, path in (("--tls-ca", ca), ("--tls-cert", cert), ("--tls-key", key)):
        if not path or not Path(path).is_file():
            return f"{option} {path}: no such file"
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    now = datetime.datetime.now(datetime.timezone.utc)
    for option, path in (("--tls-ca", ca), ("--tls-cert", cert)):
        try:
            certificate = x509.load_pem_x509_certificate(Path(str(path)).read_bytes())
        except (ValueError, OSError):
            return f"{option} {path}: not a PEM certificate"
        if certificate.not_valid_after_utc < now:  # (Zenoh would refuse it at connection time, in every child)
            return f"{option} {path}: expired on {certificate.not_valid_after_utc:%Y-%m-%d %H:%M} UTC"
    try:
        serialization.load_pem_private_key(Path(str(key)).read_bytes(), password=None)
    except (ValueError, TypeError, OSError):
        return f"--tls-key {key}: not an unencrypted PEM private key"
    return None


def secure_endpoint(endpoint: str) -> str:
    """A `tcp/HOST:PORT` endpoint as the TLS one on the same address (a closed bus carries no plain TCP)."""
    return "tls/" + endpoint[4:] if endpoint.startswith("tcp/") else endpoint


def apply(put, files: TlsFiles) -> None:
    """Set a zenoh Config's TLS and access-control sections through `put(key, value)`."""
    put("transport/link/tls/root_ca_certificate", files.ca)
    put("transport/link/tls/listen_certificate", files.cert)
    put("transport/link/tls/listen_private_key", files.key)
    put("transport/link/tls/connect_certificate", files.cert)
    put("transport/link/tls/connect_private_key", files.key)
    put("transport/link/tls/enable_mtls", True)
    put("transport/link/tls/verify_name_on_connect", False)  # the CA, not the address, names a peer (NAT, netns)
    if files.acl:
        put("access_control", json.loads(Path(files.acl).read_text()))
