"""The session's weights key: only the online learner can sign the weights a policy node acts on.

Ed25519 (``cryptography``): the learner holds the private key (``weights.key``, a PKCS#8 PEM
file readable by its owner alone), every policy node the public key (``weights.pub``). A
verifier cannot sign, so a policy node, a recorder or anyone else who is given the public
key to check weights cannot forge them; with a shared HMAC key every verifier could.

A key pair belongs to one session (``make_session_keys``, e.g. ``offline-rl weights-key DIR``;
``offline-rl hil --online`` makes a new pair in its run directory each time). Its
``session`` id, a digest of the public key, is carried in every weights message and
checked on arrival, so weights signed for another session are named as such.
"""

from __future__ import annotations

import hashlib
import os
import stat
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from ..common.atomic import atomic_path
from ..common.errors import UserError

SIGNING_KEY_FILE = "weights.key"
PUBLIC_KEY_FILE = "weights.pub"
SIGNATURE_BYTES = 64
MAX_KEY_FILE_BYTES = 4096  # a PEM Ed25519 key is about 120 bytes: anything larger is not one


def session_id(public: Ed25519PublicKey) -> str:
    """The session a key pair stands for: the first 16 bytes of SHA-256 of the raw public key, hex."""
    raw = public.public_bytes(serialization.Encoding.Raw, serialization.PublicFormat.Raw)
    return hashlib.sha256(raw).hexdigest()[:32]


class Signer:
    """Signs weights messages with the session's private key (the learner)."""

    def __init__(self, key: Ed25519PrivateKey):
        self._key = key
        self.session = session_id(key.public_key())

    @classmethod
    def generate(cls) -> "Signer":
        return cls(Ed25519PrivateKey.generate())

    def sign(self, data: bytes) -> bytes:
        return self._key.sign(bytes(data))

    def verifier(self) -> "Verifier":
        return Verifier(self._key.public_key())


class Verifier:
    """Checks weights messages against the session's public key (a policy node)."""

    def __init__(self, key: Ed25519PublicKey):
        self._key = key
        self.session = session_id(key)

    def verify(self, data, signature) -> bool:
        try:
            self._key.verify(bytes(signature), bytes(data))
        except InvalidSignature:
            return False
        return True


@dataclass(frozen=True)
class SessionKeys:
    signing_key: Path  # the learner's (mode 0600)
    public_key: Path  # every policy node's


def make_session_keys(directory: str | os.PathLike) -> SessionKeys:
    """A new key pair for one session in ``directory`` (made 0700 if new); a pair already
    there is replaced, so no two sessions share one."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True, mode=0o700)
    key = Ed25519PrivateKey.generate()
    private_pem = key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                    serialization.NoEncryption())
    public_pem = key.public_key().public_bytes(serialization.Encoding.PEM,
                                               serialization.PublicFormat.SubjectPublicKeyInfo)
    keys = SessionKeys(directory / SIGNING_KEY_FILE, directory / PUBLIC_KEY_FILE)
    # created 0600 from the first byte (never readable by others, not even for a moment),
    # then renamed over the old key
    tmp = directory / f".{SIGNING_KEY_FILE}.{os.getpid()}.tmp"
    tmp.unlink(missing_ok=True)
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(private_pem)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, keys.signing_key)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    with atomic_path(keys.public_key) as tmp_pub:
        tmp_pub.write_bytes(public_pem)
    return keys


def _read_key_file(path: str | os.PathLike, what: str, private: bool) -> bytes:
    path = Path(path)
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
    except FileNotFoundError:
        raise UserError(f"{path}: no such {what} file (offline-rl weights-key DIR makes a session's pair)") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read the {what} ({exc.strerror})") from None
    with os.fdopen(fd, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise UserError(f"{path}: not a regular file; expected the {what}")
        if private and (st.st_mode & 0o077 or st.st_uid != os.getuid()):
            raise UserError(f"{path}: the {what} must be owned by this user and readable by no one else "
                            f"(mode {stat.S_IMODE(st.st_mode):04o}; chmod 600 {path})")
        data = f.read(MAX_KEY_FILE_BYTES + 1)
    if len(data) > MAX_KEY_FILE_BYTES:
        raise UserError(f"{path}: larger than any {what}")
    return data


def load_signer(path: str | os.PathLike) -> Signer:
    """The learner's signing key from its PEM file (refused unless readable by its owner alone)."""
    data = _read_key_file(path, "weights signing key", private=True)
    try:
        key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, TypeError) as exc:
        raise UserError(f"{path}: not a PEM private key ({str(exc)[:80]})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise UserError(f"{path}: not an Ed25519 private key")
    return Signer(key)


def load_verifier(path: str | os.PathLike) -> Verifier:
    """A policy node's public key from its PEM file."""
    data = _read_key_file(path, "weights public key", private=False)
    try:
        key = serialization.load_pem_public_key(data)
    except (ValueError, TypeError) as exc:
        raise UserError(f"{path}: not a PEM public key ({str(exc)[:80]})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise UserError(f"{path}: not an Ed25519 public key")
    return Verifier(key)
