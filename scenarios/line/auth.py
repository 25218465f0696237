"""Who may log in to the line station, and as what: the station file's ``[[line.users]]``.

Passwords are kept as scrypt hashes (hashlib.scrypt, RFC 7914; n = 2^14, r = 8, p = 1, a
16-byte random salt): ``scrypt$n$r$p$salt_hex$hash_hex``. `aimbench station --hash-password`
prints one for the station file. Comparison in constant time (hmac.compare_digest).
"""

from __future__ import annotations

import hashlib
import hmac
import os
from dataclasses import dataclass

from twin.core.errors import AimbenchError

_N, _R, _P = 2**14, 8, 1

#: What each role may do on the station (the web pages, the HTTP/JSON endpoint, OPC UA).
PERMISSIONS = {
    "operator": {"inspect"},
    "plc": {"inspect"},
    "engineer": {"inspect", "engineer", "set_batch", "acknowledge"},
}


def hash_password(password: str, salt: bytes | None = None) -> str:
    """The station file's form of a password: ``scrypt$n$r$p$salt$hash``."""
    if not password:
        raise AimbenchError("an empty password cannot be hashed; give one")
    salt = os.urandom(16) if salt is None else salt
    digest = hashlib.scrypt(password.encode(), salt=salt, n=_N, r=_R, p=_P, dklen=32)
    return f"scrypt${_N}${_R}${_P}${salt.hex()}${digest.hex()}"


def verify_password(password: str, stored: str) -> bool:
    try:
        kind, n, r, p, salt, digest = stored.split("$")
        if kind != "scrypt":
            return False
        got = hashlib.scrypt(password.encode(), salt=bytes.fromhex(salt), n=int(n), r=int(r),
                             p=int(p), dklen=len(digest) // 2)
    except (ValueError, TypeError):
        return False
    return hmac.compare_digest(got.hex(), digest)


@dataclass(frozen=True)
class User:
    name: str
    role: str

    def may(self, action: str) -> bool:
        return action in PERMISSIONS.get(self.role, set())


def authenticate(station: object, name: str, password: str) -> User | None:
    """The user of the station file with this name and password, or None."""
    for u in station.line.users:  # type: ignore[attr-defined]
        if u.name == name and verify_password(password, u.password_scrypt):
            return User(u.name, u.role)
    return None
