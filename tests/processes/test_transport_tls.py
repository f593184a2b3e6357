"""The closed bus's parts without a flight (mars_link.transport.tls): the per-run secrets are private and
gone at close; real Zenoh sessions with the run's certificates and access-control list pass what each
role may send and drop the rest, whoever's key expression a sender picks; bad TLS options are one line."""

from __future__ import annotations

import datetime
import time
from pathlib import Path

from mars_link.transport import LinkSpec
from mars_link.transport.tls import RunCertificates, check_user_files, files_for
from mars_link.transport.zenoh_link import ZenohParams, free_tcp_port, make_config, open_session

FLEET = "t"


def test_run_secrets_are_private_and_removed_at_close(tmp_path: Path) -> None:
    certs = RunCertificates.create(FLEET, [[1], [2, 3]], signing_key=True)
    try:
        d = certs.directory
        assert d.stat().st_mode & 0o777 == 0o700
        names = {p.name for p in d.iterdir()}
        assert names == {"ca.crt", "acl.json", "signing.key"} | {f"{r}.{x}" for r in
                                                                 ("world", "coordinator", "unit-1", "unit-2", "unit-3")
                                                                 for x in ("crt", "key")}  # no router, no CA key
        assert all(p.stat().st_mode & 0o777 == 0o600 for p in d.iterdir())
        assert len(certs.signing_key_file.read_bytes()) == 32
        saved = certs.save(tmp_path / "run")
        assert saved.stat().st_mode & 0o777 == 0o700 and {p.name for p in saved.iterdir()} == names
        assert all(p.stat().st_mode & 0o777 == 0o600 for p in saved.iterdir())
    finally:
        certs.close()
    assert not d.exists()


def _session(certs: RunCertificates, node: str, listen: str | None = None, connect: tuple[str, ...] = ()):
    return open_session(make_config(ZenohParams(node=node, fleet=FLEET, listen=(listen,) if listen else (),
                                                connect=connect, tls=files_for(str(certs.directory), None, None,
                                                                               None, node))))


def _wait_for(condition, timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.02)


def test_the_acl_passes_each_role_its_own_keys_and_drops_the_rest() -> None:
    """World listening, units 1 and 2 connected with their own certificates: unit 1's frames on its own key
    reach the world; unit 1 publishing as unit 2 or as the coordinator reaches nobody; unit 1 cannot read
    unit 2's downlink, unit 2 reads its own."""
    certs = RunCertificates.create(FLEET, [[1], [2]])
    f = f"mars/{FLEET}"
    world_endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    sessions = []
    try:
        world = _session(certs, "world", listen=world_endpoint)
        sessions.append(world)
        got: dict[str, list[bytes]] = {}

        def keep(name):
            return lambda s: got.setdefault(name, []).append(s.payload.to_bytes())

        world.declare_subscriber(f"{f}/unit/*/mavlink/up/world", keep("world<-units"))
        world.declare_subscriber(f"{f}/world/mavlink/down/*", keep("world<-nodes"))
        unit1, unit2 = (_session(certs, f"unit/{u}", connect=(world_endpoint,)) for u in (1, 2))
        sessions += [unit1, unit2]
        unit1.declare_subscriber(f"{f}/unit/2/mavlink/down/*", keep("unit1 reads unit2"))
        unit2.declare_subscriber(f"{f}/unit/2/mavlink/down/*", keep("unit2 reads unit2"))
        _wait_for(lambda: len(list(world.info.peers_zid())) == 2)
        time.sleep(0.5)  # (the subscriptions announced)
        for _ in range(20):
            unit1.put(f"{f}/unit/1/mavlink/up/world", b"own")
            unit1.put(f"{f}/unit/2/mavlink/up/world", b"as unit 2")
            unit1.put(f"{f}/world/mavlink/down/coordinator", b"as the coordinator")
            world.put(f"{f}/unit/2/mavlink/down/world", b"to unit 2")
            time.sleep(0.01)
        _wait_for(lambda: len(got.get("world<-units", [])) >= 20 and len(got.get("unit2 reads unit2", [])) >= 20)
        time.sleep(0.3)
        assert got.get("world<-units") == [b"own"] * 20  # never "as unit 2"
        assert "world<-nodes" not in got  # never "as the coordinator"
        assert got.get("unit2 reads unit2") == [b"to unit 2"] * 20
        assert "unit1 reads unit2" not in got
    finally:
        for s in sessions:
            s.close()
        certs.close()


def test_bus_names_what_summary_json_says() -> None:
    assert LinkSpec("zenoh", tls_dir="d").bus() == "tls+acl"
    assert LinkSpec("zenoh", tls_ca="ca").bus() == "tls"
    assert LinkSpec("zenoh", insecure=True).bus() == "insecure"
    assert LinkSpec("udp").bus() == "udp"


def _expired_certificate(tmp_path: Path) -> tuple[Path, Path]:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "old")])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(name).issuer_name(name).public_key(key.public_key())
            .serial_number(1).not_valid_before(now - datetime.timedelta(days=3))
            .not_valid_after(now - datetime.timedelta(days=1)).sign(key, hashes.SHA256()))
    cert_path, key_path = tmp_path / "old.crt", tmp_path / "old.key"
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    key_path.write_bytes(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                           serialization.NoEncryption()))
    return cert_path, key_path


def test_bad_tls_options_are_one_line_and_exit_2(tmp_path: Path, capsys) -> None:
    from mars_link.apps.cli import main

    certs = RunCertificates.create(FLEET, [[1]])
    try:
        d = certs.directory
        good = ["--tls-ca", str(d / "ca.crt"), "--tls-cert", str(d / "world.crt"), "--tls-key", str(d / "world.key")]
        assert check_user_files(*good[1::2]) is None
        old_cert, old_key = _expired_certificate(tmp_path)
        junk = tmp_path / "junk.pem"
        junk.write_text("not a certificate")
        cases = {"go together": ["--tls-ca", str(d / "ca.crt")],
                 "no such file": ["--tls-ca", str(tmp_path / "nope"), *good[2:]],
                 "not a PEM certificate": [*good[:3], str(junk), *good[4:]],
                 "expired": [*good[:3], str(old_cert), "--tls-key", str(old_key)],
                 "private key": [*good[:5], str(junk)],
                 "closed Zenoh bus": [*good, "--insecure"]}
        for words, options in cases.items():
            assert main(["run", "hover_1x1", "--mode", "sitl", *options, "--out", str(tmp_path / "o")]) == 2, words
            err = capsys.readouterr().err
            assert len(err.strip().splitlines()) == 1 and words in err and "Traceback" not in err, (words, err)
            assert not (tmp_path / "o").exists()
    finally:
        certs.close()


def test_an_external_coordinator_needs_the_bus_credentials_or_insecure(tmp_path: Path, capsys) -> None:
    from mars_link.apps.cli import main

    code = main(["coordinator", "hover_1x1", "--zenoh-connect", "tcp/127.0.0.1:9", "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2 and "--tls-ca" in err and "--insecure" in err and len(err.strip().splitlines()) == 1


def test_require_signing_without_the_users_key_is_one_line_and_exit_2(tmp_path: Path, capsys, monkeypatch) -> None:
    """The per-run key is nobody else's: clients could not sign with it, so --require-signing wants the user's."""
    from mars_link.apps.cli import main
    from mars_link.mavlink.signing import DEFAULT_KEY_ENV

    monkeypatch.delenv(DEFAULT_KEY_ENV, raising=False)
    assert main(["sitl", "up", "hover_1x1", "--require-signing", "--any-bind", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--signing-key-file" in err and "Traceback" not in err, err
