"""The line station's secured OPC UA endpoint trusts only the client certificates its trust list
names (`[line.opcua] trust_list`), checked with real asyncua clients against the real server
(`scenarios.line.opcua.StationOpcUa` on a real `StationEngine` and store; no inspection runs,
so no twin scans): a trusted PLC connects; an untrusted one is refused with
BadCertificateUntrusted and the refusal is in the audit trail; its certificate copied into the
folder, it connects without a restart; a certificate issued by a trusted CA is trusted; a
client that opens the channel with an untrusted certificate and names none at CreateSession is
refused at ActivateSession; an anonymous station still takes anonymous clients."""

from __future__ import annotations

import asyncio
import json
import shutil
import socket
from pathlib import Path

import pytest

pytest.importorskip("asyncua")

from asyncua import Client, ua
from asyncua.crypto import cert_gen
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256
from cryptography import x509
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.serialization import Encoding
from cryptography.x509.oid import ExtendedKeyUsageOID

from scenarios import station as stations
from scenarios.line import auth
from scenarios.line.engine import StationEngine
from scenarios.line.opcua import StationOpcUa

PASSWORD = "plc-secret-1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def secured_station() -> stations.Station:
    return stations.from_dict({"name": "opcua-ci", "line": {
        "opcua": {"anonymous": False},
        "users": [{"name": "plc1", "role": "plc",
                   "password_scrypt": auth.hash_password(PASSWORD)}]}})


async def client_cert(folder: Path, name: str, uri: str) -> tuple[Path, Path]:
    """A PLC's self-signed application instance certificate, as a PLC makes its own."""
    cert, key = folder / f"{name}-cert.der", folder / f"{name}-key.pem"
    await cert_gen.setup_self_signed_certificate(
        key, cert, uri, "localhost", [ExtendedKeyUsageOID.CLIENT_AUTH], {"commonName": name})
    return cert, key


def ca_issued_cert(folder: Path, uri: str) -> tuple[Path, Path, Path]:
    """A plant CA's certificate and a PLC certificate it issued (the PLC's key beside it)."""
    ca_key = cert_gen.generate_private_key()
    ca = cert_gen.generate_self_signed_app_certificate(
        ca_key, "plant CA", {}, [x509.UniformResourceIdentifier("urn:plant:ca")], [])
    key = cert_gen.generate_private_key()
    csr = cert_gen.generate_app_certificate_signing_request(
        key, "plc by the plant CA", {}, [x509.UniformResourceIdentifier(uri),
                                         x509.DNSName("localhost")],
        [ExtendedKeyUsageOID.CLIENT_AUTH])
    leaf = cert_gen.sign_certificate_request(csr, ca, ca_key)
    paths = folder / "plant-ca.der", folder / "ca-plc-cert.der", folder / "ca-plc-key.pem"
    paths[0].write_bytes(ca.public_bytes(Encoding.DER))
    paths[1].write_bytes(leaf.public_bytes(Encoding.DER))
    paths[2].write_bytes(cert_gen.dump_private_key_as_pem(key))
    return paths


async def connect(url: str, cert: Path, key: Path, uri: str,
                  password: str = PASSWORD) -> Client:
    client = Client(url, timeout=20)
    client.application_uri = uri
    client.set_user("plc1")
    client.set_password(password)
    await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                              mode=ua.MessageSecurityMode.SignAndEncrypt)
    await client.connect()
    return client


async def read_state(client: Client) -> str:
    idx = await client.get_namespace_index("urn:aimbench:line-station")
    return await client.get_node(f"ns={idx};s=Station.State").read_value()


def refusals(engine: StationEngine) -> list[dict]:
    rows = [r for r in engine.audit_rows() if r["action"] == "opcua certificate refused"]
    return [r["detail"] if isinstance(r["detail"], dict) else json.loads(r["detail"])
            for r in rows]


@pytest.fixture
def served(tmp_path):
    """A secured station's OPC UA server, its engine and its folder, on a free port."""
    engine = StationEngine(secured_station(), tmp_path / "line.sqlite")
    folder = tmp_path / "line.station"
    opc = StationOpcUa(engine, "127.0.0.1", free_port(), folder)
    yield engine, opc, folder
    engine.close()


def test_only_clients_in_the_trust_list_connect(served, tmp_path):
    engine, opc, folder = served
    url = f"opc.tcp://127.0.0.1:{opc.port}/aimbench/station"
    pki = tmp_path / "plc-side"
    pki.mkdir()

    async def run() -> None:
        engine._loop = asyncio.get_running_loop()
        await opc.start()
        try:
            trusted = await client_cert(pki, "plc-a", "urn:plant:plc-a")
            stranger = await client_cert(pki, "plc-b", "urn:plant:plc-b")
            trust = folder / "opcua-trusted"
            assert trust.is_dir() and not any(trust.iterdir())  # created empty: nobody yet
            shutil.copy(trusted[0], trust)  # the engineer adds PLC A's certificate

            client = await connect(url, *trusted, "urn:plant:plc-a")
            try:
                assert await read_state(client) == "idle"
            finally:
                await client.disconnect()

            # PLC B, with the right user and password but a certificate nobody trusted
            with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
                await connect(url, *stranger, "urn:plant:plc-b")
            seen = refusals(engine)
            assert seen and seen[-1]["why"] == "BadCertificateUntrusted"
            assert seen[-1]["subject"].startswith("CN=plc-b,")
            assert seen[-1]["thumbprint"] == x509.load_der_x509_certificate(
                stranger[0].read_bytes()).fingerprint(hashes.SHA1()).hex()

            # trusted while the station runs: the next session reads the folder again
            shutil.copy(stranger[0], trust)
            client = await connect(url, *stranger, "urn:plant:plc-b")
            await client.disconnect()

            # the trust is in the certificate, not the password: a trusted PLC with a wrong
            # password is still refused
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await connect(url, *trusted, "urn:plant:plc-a", password="not-it")

            # a certificate whose URI is not the client's application URI is refused too
            with pytest.raises(ua.uaerrors.BadCertificateUriInvalid):
                await connect(url, *trusted, "urn:plant:someone-else")

            # a PLC whose certificate the plant's CA issued: trusted through the CA alone
            ca, leaf, leaf_key = ca_issued_cert(pki, "urn:plant:plc-c")
            with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
                await connect(url, leaf, leaf_key, "urn:plant:plc-c")
            shutil.copy(ca, trust)
            client = await connect(url, leaf, leaf_key, "urn:plant:plc-c")
            await client.disconnect()
        finally:
            await opc.stop()

    asyncio.run(run())


def test_a_session_that_names_no_certificate_is_judged_by_its_channel(served, tmp_path):
    """asyncua's server checks the certificate a client names at CreateSession and skips the
    check when none is named; the channel's own certificate is checked again at login."""
    engine, opc, _ = served
    url = f"opc.tcp://127.0.0.1:{opc.port}/aimbench/station"

    async def run() -> None:
        engine._loop = asyncio.get_running_loop()
        await opc.start()
        try:
            cert, key = await client_cert(tmp_path, "sly", "urn:plant:sly")
            client = Client(url, timeout=20)
            client.application_uri = "urn:plant:sly"
            client.set_user("plc1")
            client.set_password(PASSWORD)
            await client.set_security(SecurityPolicyBasic256Sha256, str(cert), str(key),
                                      mode=ua.MessageSecurityMode.SignAndEncrypt)
            send = client.uaclient.create_session

            async def create_session_naming_no_certificate(params):
                params.ClientCertificate = None
                return await send(params)

            client.uaclient.create_session = create_session_naming_no_certificate
            with pytest.raises(ua.uaerrors.BadUserAccessDenied):
                await client.connect()
            assert refusals(engine)[-1]["why"] == "the channel's certificate is not trusted"
        finally:
            await opc.stop()

    asyncio.run(run())


def test_an_anonymous_station_takes_anonymous_clients_without_certificates(tmp_path):
    engine = StationEngine(stations.from_dict({"name": "open-cell"}), tmp_path / "line.sqlite")
    opc = StationOpcUa(engine, "127.0.0.1", free_port(), tmp_path / "line.station")

    async def run() -> None:
        engine._loop = asyncio.get_running_loop()
        await opc.start()
        try:
            assert opc.trust is None
            client = Client(f"opc.tcp://127.0.0.1:{opc.port}/aimbench/station", timeout=20)
            await client.connect()
            try:
                assert await read_state(client) == "idle"
            finally:
                await client.disconnect()
        finally:
            await opc.stop()

    try:
        asyncio.run(run())
    finally:
        engine.close()
    assert not (tmp_path / "line.station" / "opcua-trusted").exists()


def test_a_file_in_the_trust_list_that_is_no_certificate(served, tmp_path):
    """At start it stops the station, naming the folder; dropped in while the station runs,
    the trust list read before stands: the trusted PLC still connects, no one new does."""
    from twin.core.errors import AimbenchError

    engine, opc, folder = served
    url = f"opc.tcp://127.0.0.1:{opc.port}/aimbench/station"
    trust = folder / "opcua-trusted"

    async def run() -> None:
        engine._loop = asyncio.get_running_loop()
        trusted = await client_cert(tmp_path, "plc-a", "urn:plant:plc-a")
        trust.mkdir(parents=True)
        (trust / "notes.pem").write_text("not a certificate\n")
        with pytest.raises(AimbenchError, match="opcua-trusted"):
            await opc.start()
        await opc.stop()
        (trust / "notes.pem").unlink()
        shutil.copy(trusted[0], trust)
        await opc.start()
        try:
            (trust / "notes.pem").write_text("not a certificate\n")
            newcomer = await client_cert(tmp_path, "plc-b", "urn:plant:plc-b")
            shutil.copy(newcomer[0], trust)
            client = await connect(url, *trusted, "urn:plant:plc-a")
            await client.disconnect()
            with pytest.raises(ua.uaerrors.BadCertificateUntrusted):
                await connect(url, *newcomer, "urn:plant:plc-b")
        finally:
            await opc.stop()

    asyncio.run(run())
