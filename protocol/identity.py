"""The service's identity: a key pair whose public half a robot is configured with.

A robot that knows its service's key (its fingerprint, as ``serve`` prints it) checks that what
answers is that service: its info and every open's reply carry an Ed25519 signature. The open
agrees the session's secret by X25519 with a key the robot makes for that open alone, so the
secret never travels: a peer that relays the open to the service learns nothing it can sign with.
The service then proves each estimate with an HMAC under that secret. A robot may keep its key
(``RobotKey.load_or_create``) so that the service knows it again: each open then carries a proof
that its sender holds the key, fresh on the service's clock, and the service counts its caps per
key. The primitives are the ``cryptography`` package's; nothing here is cryptography of our own.
"""

from __future__ import annotations

import base64
import hashlib
import hmac
import os
import tempfile
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey
from cryptography.hazmat.primitives.asymmetric.x25519 import X25519PrivateKey, X25519PublicKey
from cryptography.hazmat.primitives.kdf.hkdf import HKDF
from pydantic import BaseModel

from .codec import encode

__all__ = ["RobotKey", "ServiceKey", "fingerprint", "matches", "signed", "verified", "verify_signature"]

_RAW = {"encoding": serialization.Encoding.Raw, "format": serialization.PublicFormat.Raw}


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def _halves(public: str) -> tuple[Ed25519PublicKey, X25519PublicKey]:
    """A service's public key (base64 of Ed25519's 32 bytes, then X25519's 32); ValueError if not one."""
    try:
        raw = base64.b64decode(public, validate=True)
    except ValueError:
        raw = b""
    if len(raw) != 64:
        raise ValueError(f"service key: expected 64 bytes in base64, got {len(raw)}")
    return Ed25519PublicKey.from_public_bytes(raw[:32]), X25519PublicKey.from_public_bytes(raw[32:])


def fingerprint(public: str) -> str:
    """What a robot is configured with: the first 16 bytes of the public key's SHA-256, as hex in
    groups of four (``3f2a-9c01-...``); a ValueError for a key that is not base64."""
    digest = hashlib.sha256(base64.b64decode(public, validate=True)).hexdigest()[:32]
    return "-".join(digest[i : i + 4] for i in range(0, 32, 4))


def matches(configured: str, public: str) -> bool:
    """Whether ``public`` is the key a robot was configured with: the key itself (base64, exactly)
    or its fingerprint (in any case, ``:`` or ``-`` between groups)."""
    if not public:
        return False
    if configured.strip() == public:
        return True
    try:
        return configured.strip().lower().replace(":", "-") == fingerprint(public)
    except ValueError:  # not base64: no key of any service
        return False


def _secret(shared: bytes, session: str) -> str:
    kdf = HKDF(algorithm=hashes.SHA256(), length=16, salt=None, info=b"inhand-tracker session " + session.encode())
    return kdf.derive(shared).hex()


def verify_signature(public: str, data: bytes, signature: str) -> bool:
    """Whether ``signature`` (base64) is the service's of ``data``."""
    try:
        _halves(public)[0].verify(base64.b64decode(signature), data)
    except (InvalidSignature, ValueError):
        return False
    return True


class ServiceKey:
    """The service's private keys: Ed25519 signs what it answers, X25519 agrees a secret per open."""

    def __init__(self, sign: Ed25519PrivateKey, agree: X25519PrivateKey):
        self._sign, self._agree = sign, agree
        self.public = _b64(sign.public_key().public_bytes(**_RAW) + agree.public_key().public_bytes(**_RAW))
        """Both public halves, base64: what the service's info carries."""
        self.fingerprint = fingerprint(self.public)
        """What ``serve`` prints and a robot is configured with."""

    @classmethod
    def generate(cls) -> ServiceKey:
        return cls(Ed25519PrivateKey.generate(), X25519PrivateKey.generate())

    @classmethod
    def load_or_create(cls, path: str | os.PathLike) -> ServiceKey:
        """The key kept in ``path`` (64 raw bytes, readable by the owner alone), made there on the
        first start; an OSError or ValueError names the file."""
        raw = _key_file(path, 64, "key_file", lambda: (k := cls.generate())._sign.private_bytes_raw()
                        + k._agree.private_bytes_raw())  # fmt: skip
        return cls(Ed25519PrivateKey.from_private_bytes(raw[:32]), X25519PrivateKey.from_private_bytes(raw[32:]))

    def sign(self, data: bytes) -> str:
        """The Ed25519 signature of ``data``, base64."""
        return _b64(self._sign.sign(data))

    def session_secret(self, client_key: str, session: str) -> str:
        """The secret of ``session`` agreed with the robot's key for this open (base64 X25519, as
        :attr:`protocol.OpenSession.client_key` checks it)."""
        return _secret(self._shared(client_key), session)

    def proven(self, request: BaseModel) -> bool:
        """Whether an open's ``proof`` was made with the private half of its ``client_key``."""
        return bool(request.proof) and hmac.compare_digest(request.proof, _proof(self._shared(request.client_key),
                                                                                 request))  # fmt: skip

    def _shared(self, client_key: str) -> bytes:
        return self._agree.exchange(X25519PublicKey.from_public_bytes(base64.b64decode(client_key, validate=True)))


class RobotKey:
    """A robot's X25519 key: made for one open, or kept in a file so that the service knows the
    robot again by it (its caps, its names, room kept for it: the service's ``robot_keys``)."""

    def __init__(self, key: X25519PrivateKey | None = None):
        self._key = key or X25519PrivateKey.generate()
        self.public = _b64(self._key.public_key().public_bytes(**_RAW))
        """What the open carries (:attr:`protocol.OpenSession.client_key`)."""
        self.fingerprint = fingerprint(self.public)
        """What a service's ``robot_keys`` lists for this robot."""

    @classmethod
    def load_or_create(cls, path: str | os.PathLike) -> RobotKey:
        """The key kept in ``path`` (32 raw bytes, readable by the owner alone), made there on first use."""
        return cls(X25519PrivateKey.from_private_bytes(_key_file(path, 32, "identity", lambda: cls()._raw())))

    def _raw(self) -> bytes:
        return self._key.private_bytes_raw()

    def secret(self, service_public: str, session: str) -> str:
        """The session's secret, as the service derives it."""
        return _secret(self._key.exchange(_halves(service_public)[1]), session)

    def prove(self, service_public: str, request: BaseModel) -> BaseModel:
        """``request`` (an open carrying this key) with its ``proof``: an HMAC only the holders of
        this key's and the service's private halves can make, over everything else it says."""
        return request.model_copy(update={"proof": _proof(self._key.exchange(_halves(service_public)[1]), request)})


def _proof(shared: bytes, request: BaseModel) -> str:
    kdf = HKDF(algorithm=hashes.SHA256(), length=32, salt=None, info=b"inhand-tracker open")
    bare = request.model_copy(update={"proof": ""})
    return _b64(hmac.digest(kdf.derive(shared), encode(bare), "sha256"))


def _key_file(path: str | os.PathLike, size: int, field: str, make) -> bytes:
    """The ``size`` raw bytes kept in ``path`` (readable by the owner alone), written there by
    ``make()`` on first use; an OSError or ValueError names the file."""
    path = Path(path).expanduser()
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        # Written aside and linked into place: processes starting together on a fresh machine all
        # end up with the one key that was linked first, never a half-written one.
        fd, aside = tempfile.mkstemp(dir=path.parent, prefix=".key-")
        try:
            with os.fdopen(fd, "wb") as f:
                f.write(make())
            os.link(aside, path)
        except FileExistsError:
            pass
        finally:
            os.unlink(aside)
    raw = path.read_bytes()
    if len(raw) != size:
        raise ValueError(f"{field}: '{path}' holds {len(raw)} bytes, not a key of {size}")
    return raw


def signed(key: ServiceKey, message: BaseModel, bound: str = "") -> BaseModel:
    """``message`` (with a ``signature`` field) signed by the service, over its encoding with the
    signature empty and then ``bound`` (what it answers: an open's client key)."""
    bare = message.model_copy(update={"signature": ""})
    return bare.model_copy(update={"signature": key.sign(encode(bare) + bound.encode())})


def verified(public: str, message: BaseModel, bound: str = "") -> bool:
    """Whether ``message`` carries the signature of the service whose public key is ``public``."""
    bare = message.model_copy(update={"signature": ""})
    return bool(message.signature) and verify_signature(public, encode(bare) + bound.encode(), message.signature)
