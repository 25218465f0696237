"""The line station's OPC UA server (asyncua): the PLC's handshake, in the spirit of OPC 40450-1
(the machine-vision companion specification): the PLC writes the part's id and a start, the
station answers with its state, and with the verdict and each axis's value, expanded
uncertainty, limit and verdict. Errors are states, never silence.

Address space (namespace ``urn:aimbench:line-station``), under ``Objects/Station``:

- PartId (String, the PLC writes): the unit to inspect next (a VIN, a serial).
- Start (Boolean, the PLC writes): true = inspect PartId now; the station sets it back to
  false once taken (or refused).
- State (String): idle, busy, done or error; Busy, Done, Error, Refused (Boolean): the same
  as flags, Refused meaning the last Start was refused (busy, a bad id).
- Message (String): why (an error, a refusal, the verdict's reason).
- ResultPartId (String), Verdict (String: pass, fail, inconclusive), RecordId (Int64: the
  record in the station's store), ResultCounter (UInt32: the PLC's results since the station
  started). These and Done belong to the parts the PLC started: a unit inspected from the
  page or by MES changes State and Busy, not them; Done stays true until the PLC's next
  accepted Start.
- Axes/AXIS/Value, Uncertainty, Limit (Double) and Verdict (String), AXIS one of the judged
  axes named with their unit (x_mm, roll_deg, tilt_deg, yaw_deg...): the mounting error,
  U = k u, the limit and that axis's verdict.

The results are written before Done turns true, so a PLC that sees Done reads a whole result.
Security: anonymous and no security policy only when the station file says
``[line.opcua] anonymous = true``; otherwise users of role ``plc`` log in by name and password,
over Basic256Sha256 SignAndEncrypt only, with the station's certificate (self-signed, generated
on first start when the files named do not exist), and only from a client whose application
instance certificate is trusted: in the station's trust list (``[line.opcua] trust_list``, a
folder of client certificates or of the CAs that issued them), within its validity, its URI the
client's application URI, its key usage an OPC UA client's (OPC 10000-6 6.2.2; asyncua's
`CertificateValidator` with `TRUSTED_VALIDATION`). Any other is refused (BadCertificateUntrusted
and its kin) and the refusal written to the audit trail.
"""

from __future__ import annotations

import asyncio
import logging
import socket
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import User as UaUser
from asyncua.crypto.permission_rules import UserRole
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from cryptography import x509
from cryptography.hazmat.primitives import hashes

from scenarios.line import auth
from scenarios.line.engine import Busy, Snapshot, StationEngine
from twin.core.errors import AimbenchError

NAMESPACE = "urn:aimbench:line-station"
APP_URI = "urn:aimbench:line-station:server"


def describe(cert: x509.Certificate) -> dict[str, str]:
    """What the audit trail and the refusal say of a certificate: its subject and its SHA-1
    thumbprint (the one OPC UA tools show)."""
    return {"subject": cert.subject.rfc4514_string(),
            "thumbprint": cert.fingerprint(hashes.SHA1()).hex()}  # OPC UA names certs by SHA-1


class StationTrust:
    """Which clients the secured endpoint talks to: those whose certificate is trusted by the
    folder `folder` (a certificate there, or the CA that issued it), checked by asyncua's
    `CertificateValidator` at CreateSession and, for the certificate that actually secures
    the channel, again at ActivateSession (`channel_trusted`): a client could otherwise open
    the channel with one certificate and create its session naming none."""

    OPTIONS = (CertificateValidatorOptions.TRUSTED_VALIDATION
               | CertificateValidatorOptions.PEER_CLIENT)

    def __init__(self, folder: Path, audit: Any) -> None:
        self.folder = folder
        self.audit = audit  # StationEngine.audit
        self.store = TrustStore([folder], [])  # loaded by `load`: trusts no one until then
        self.validator = CertificateValidator(self.OPTIONS, self.store)

    async def load(self) -> None:
        """Read the trust list's folder (created empty if missing). A file there that is no
        certificate raises AimbenchError naming it."""
        self.folder.mkdir(parents=True, exist_ok=True)
        store = TrustStore([self.folder], [])
        try:
            await store.load_trust()
        except ValueError as exc:
            # cryptography refuses an empty store; a fresh TrustStore trusts no one, which
            # is what an empty trust list means
            if "empty store" not in str(exc):
                raise AimbenchError(f"the OPC UA trust list {self.folder}: {exc}") from exc
        except Exception as exc:
            raise AimbenchError(f"the OPC UA trust list {self.folder}: {exc}") from exc
        self.store = store
        self.validator = CertificateValidator(self.OPTIONS, store)

    async def __call__(self, cert: x509.Certificate,
                       app: ua.ApplicationDescription) -> None:
        """asyncua's certificate validator (`Server.set_certificate_validator`): raises
        ServiceError with the OPC UA status that says why a client is refused."""
        # read the folder again: an engineer who adds a PLC's certificate needs no restart
        try:
            await self.load()
        except AimbenchError as exc:
            # a bad file dropped in neither locks the line out nor trusts anyone new
            logging.getLogger(__name__).warning("%s; the trust list read before stands", exc)
        try:
            await self.validator.validate(cert, app)
        except ServiceError as exc:
            why = ua.StatusCode(exc.code).name
            self.audit("plc", "plc", "opcua certificate refused",
                       {**describe(cert), "application_uri": app.ApplicationUri, "why": why})
            logging.getLogger(__name__).warning(
                "OPC UA client %s refused: %s (put its certificate in %s to trust it)",
                describe(cert)["subject"], why, self.folder)
            raise

    def channel_trusted(self, der: bytes | None) -> bool:
        """Whether the certificate that secures a session's channel is in the trust list (the
        store as the last session read it)."""
        if not der:
            return False
        cert = x509.load_der_x509_certificate(der)
        now = datetime.now(UTC)
        if (self.store.validate(cert)
                and cert.not_valid_before_utc <= now <= cert.not_valid_after_utc):
            return True
        self.audit("plc", "plc", "opcua certificate refused",
                   {**describe(cert), "why": "the channel's certificate is not trusted"})
        return False


class _StationUsers:
    """asyncua's user manager: the station file's users of role ``plc``, over a channel
    secured by a trusted client certificate."""

    def __init__(self, station: Any, trust: StationTrust) -> None:
        self.station = station
        self.trust = trust

    def get_user(self, iserver: Any, username: str | None = None, password: str | None = None,
                 certificate: bytes | None = None) -> UaUser | None:
        if not username or password is None:
            return None
        # asyncua hands over the channel's certificate for a user-name token
        if not self.trust.channel_trusted(certificate):
            return None
        user = auth.authenticate(self.station, username, password)
        if user is None or user.role != "plc":
            return None
        return UaUser(role=UserRole.User, name=user.name)


async def station_certificate(cert: Path, key: Path, host: str) -> None:
    """The station's certificate and key, generated (self-signed) if missing."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    cert.parent.mkdir(parents=True, exist_ok=True)
    await setup_self_signed_certificate(
        key, cert, APP_URI, host, [ExtendedKeyUsageOID.SERVER_AUTH],
        {"countryName": "DE", "organizationName": "aimbench", "commonName": "aimbench station"})


class StationOpcUa:
    """The OPC UA face of one `StationEngine` (module docstring)."""

    def __init__(self, engine: StationEngine, host: str, port: int, folder: Path) -> None:
        self.engine = engine
        self.host, self.port = host, port
        self.folder = folder
        self.server: Server | None = None
        self.trust: StationTrust | None = None  # None: anonymous, no security
        self.nodes: dict[str, Any] = {}
        self.axes: dict[str, dict[str, Any]] = {}
        self._tasks: set[asyncio.Task] = set()
        self.counter = 0  # the PLC's results since the station started
        # one snapshot written whole before the next: a PLC never reads Done of one state
        # beside the flags of another
        self._writing = asyncio.Lock()

    async def start(self) -> None:
        cfg = self.engine.station.line.opcua
        logging.getLogger("asyncua").setLevel(logging.ERROR)
        # asyncua's trust store logs a traceback for every untrusted certificate; the station
        # says it in one line and in the audit trail (StationTrust)
        logging.getLogger("asyncuagds").setLevel(logging.CRITICAL)
        trust = None if cfg.anonymous else StationTrust(self._path(cfg.trust_list),
                                                        self.engine.audit)
        server = Server(user_manager=None if trust is None else _StationUsers(
            self.engine.station, trust))
        await server.init()
        server.set_endpoint(f"opc.tcp://{self.host}:{self.port}/aimbench/station")
        server.set_server_name(f"aimbench station {self.engine.station.name}")
        await server.set_application_uri(APP_URI)
        if cfg.anonymous:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            server.set_identity_tokens([ua.AnonymousIdentityToken])
        else:
            cert = self._path(cfg.certificate)
            key = self._path(cfg.private_key)
            await station_certificate(cert, key, socket.gethostname())
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
            server.set_identity_tokens([ua.UserNameIdentityToken])
            await trust.load()
            server.set_certificate_validator(trust)
            self.trust = trust
        idx = await server.register_namespace(NAMESPACE)
        obj = await server.nodes.objects.add_object(idx, "Station")

        async def var(parent: Any, name: str, value: Any, vtype: ua.VariantType,
                      writable: bool = False) -> Any:
            node = await parent.add_variable(ua.NodeId(f"Station.{name}", idx), name,
                                             ua.Variant(value, vtype))
            if writable:
                await node.set_writable()
            return node

        n = self.nodes
        n["PartId"] = await var(obj, "PartId", "", ua.VariantType.String, True)
        n["Start"] = await var(obj, "Start", False, ua.VariantType.Boolean, True)
        for name, value, vtype in (
                ("State", "idle", ua.VariantType.String),
                ("Busy", False, ua.VariantType.Boolean),
                ("Done", False, ua.VariantType.Boolean),
                ("Error", False, ua.VariantType.Boolean),
                ("Refused", False, ua.VariantType.Boolean),
                ("Message", "", ua.VariantType.String),
                ("ResultPartId", "", ua.VariantType.String),
                ("Verdict", "", ua.VariantType.String),
                ("RecordId", 0, ua.VariantType.Int64),
                ("ResultCounter", 0, ua.VariantType.UInt32)):
            n[name] = await var(obj, name, value, vtype)
        folder = await obj.add_folder(ua.NodeId("Station.Axes", idx), "Axes")
        from scenarios.inspection.verdict import edge_key, limits_si

        for a in limits_si(self.engine.station.tolerances):
            key = edge_key(a)
            ax = await folder.add_object(ua.NodeId(f"Station.Axes.{key}", idx), key)
            self.axes[key] = {
                "Value": await var(ax, f"Axes.{key}.Value", float("nan"),
                                   ua.VariantType.Double),
                "Uncertainty": await var(ax, f"Axes.{key}.Uncertainty", float("nan"),
                                         ua.VariantType.Double),
                "Limit": await var(ax, f"Axes.{key}.Limit", float("nan"),
                                   ua.VariantType.Double),
                "Verdict": await var(ax, f"Axes.{key}.Verdict", "", ua.VariantType.String)}
        await server.start()
        self.server = server
        self.engine.subscribe(self._publish)
        sub = await server.create_subscription(20, self)
        await sub.subscribe_data_change(n["Start"])
        await self._publish(self.engine.snapshot)

    def _path(self, name: str) -> Path:
        p = Path(name)
        return p if p.is_absolute() else self.folder / p

    async def stop(self) -> None:
        if self.server is not None:
            await self.server.stop()

    # -- the PLC's Start ----------------------------------------------------------------------

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        """asyncua calls this on the loop when Start changes; a true Start is taken."""
        if val is True:
            task = asyncio.ensure_future(self._start())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _start(self) -> None:
        """Take a Start: decide first (Refused and Message), then set Start back to false, so
        a PLC that sees Start false reads this attempt's Refused, never an older one's."""
        n = self.nodes
        part = await n["PartId"].read_value()
        try:
            if self.engine.busy:
                # refuse before touching the engine's state: the unit in progress stands
                raise Busy(f"busy: inspecting unit {self.engine.snapshot.unit}; {part} was "
                           "not started, set Start again when Busy is false")
            # the trigger takes the engine's lock before its first await: nothing can come
            # between this check and it
            run = asyncio.ensure_future(self.engine.trigger(part, "opcua", who="plc",
                                                            role="plc"))
        except Busy as exc:
            await n["Message"].write_value(str(exc))
            await n["Refused"].write_value(True)
            await n["Start"].write_value(False)
            self.engine.audit("plc", "plc", "refused", {"origin": "opcua", "unit": part,
                                                        "why": "busy"})
            return
        await asyncio.sleep(0)  # let the trigger take the lock and say busy
        await n["Done"].write_value(False)  # the PLC's previous result is no longer the last
        await n["Refused"].write_value(False)
        await n["Start"].write_value(False)
        try:
            await run
        except AimbenchError as exc:
            # a bad id is refused; a failed inspection is already the engine's error state
            if self.engine.snapshot.state != "error":
                await n["Message"].write_value(str(exc))
                await n["Refused"].write_value(True)
        except Exception:  # never die silently: the PLC must see an error state
            logging.getLogger(__name__).exception("the inspection of %s failed", part)

    # -- the station's state ------------------------------------------------------------------

    async def _publish(self, snap: Snapshot) -> None:
        async with self._writing:
            await self._write(snap)

    async def _write(self, snap: Snapshot) -> None:
        """The station's state to the nodes. The result nodes and Done are the PLC's own:
        they change only with a part the PLC started (the page's and MES's units do not
        overwrite them), and Done stays true until the PLC's next accepted Start, so a PLC
        never has to catch a passing moment."""
        n = self.nodes
        if not n:
            return
        r = snap.result
        if snap.state == "done" and r is not None and r.get("origin") == "opcua":
            for a in r["axes"]:
                nodes = self.axes.get(a["axis"])
                if nodes is None:
                    continue
                nan = float("nan")
                await nodes["Value"].write_value(nan if a["value"] is None else a["value"])
                await nodes["Uncertainty"].write_value(nan if a["U"] is None else a["U"])
                await nodes["Limit"].write_value(a["limit"])
                await nodes["Verdict"].write_value(a["verdict"] or "")
            await n["Verdict"].write_value(r["verdict"])
            await n["RecordId"].write_value(ua.Variant(int(r["record"]), ua.VariantType.Int64))
            await n["ResultPartId"].write_value(r["unit"])
            self.counter += 1
            await n["ResultCounter"].write_value(ua.Variant(self.counter,
                                                            ua.VariantType.UInt32))
            await n["Done"].write_value(True)
        await n["Message"].write_value(snap.message)
        await n["State"].write_value(snap.state)
        await n["Busy"].write_value(snap.state == "busy")
        await n["Error"].write_value(snap.state == "error")
