"""Who may change a robot's policy: Ed25519 signatures over pushed weights, keys in OpenSSH's file formats.

Weights are the one input that works like code on a robot, and any peer on its
DDS domain can publish on ``policy_weights`` (the Fast DDS of the Jazzy wheels
has no DDS Security). So the trainer signs what it pushes and a policy node
adopts only what a key it trusts verifies.

What is signed (``signed_payload``): a domain tag, the weights message's header
exactly as it travels (JSON: format, version, epoch, the policy's config and the
metadata with the run id) and the SHA-256 of the safetensors bytes. Changing
any of these, or moving a signature to another message kind, breaks it.

Keys are OpenSSH's: the private key is an ``-----BEGIN OPENSSH PRIVATE KEY-----``
file (mode 0600), the public key one line ``ssh-ed25519 AAAA... comment``, and
a key is named by its fingerprint as ``ssh-keygen -l`` prints it
(``SHA256:<base64>``). So ``ssh-keygen -t ed25519 -N ''`` makes usable keys
too, and ``ssh-keygen -lf`` shows which key a node trusts. PEM (PKCS#8 /
SubjectPublicKeyInfo) files are read as well.

A signature travels as one string (``Signature.label``), a JSON object
``{"signature": "ed25519", "key": <fingerprint>, "value": <base64>}``: in the
weights message's third layout dimension, and in a checkpoint's .json.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
import struct
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidSignature, UnsupportedAlgorithm
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey, Ed25519PublicKey

from morph_core.util.atomic import atomic_write_bytes

ALGORITHM = "ed25519"
DOMAIN = b"morph_policy_weights signature 1\n"
"""prefix of every signed payload: a signature made for something else never verifies here"""
MAX_SIGNATURE_CHARS = 512
"""a signature label is ~150 characters; longer ones are refused before any parsing"""
MAX_KEY_FILE_BYTES = 16 * 1024
_SIGNATURE_BYTES = 64


class KeyFileError(ValueError):
    """A key file that cannot be used; ``str(err)`` names the file and the reason."""

    def __init__(self, path: str | Path, reason: str):
        self.path, self.reason = str(path), reason
        super().__init__(f"{self.path}: {reason}")


class SignatureError(ValueError):
    """Weights whose signature does not make them trusted. ``reason`` is a short fixed word (counted on
    /diagnostics: ``unsigned``, ``signature_malformed``, ``untrusted_key``, ``bad_signature``), ``str(err)``
    says why in a sentence."""

    def __init__(self, reason: str, detail: str):
        self.reason = reason
        super().__init__(detail)


def fingerprint(key: Ed25519PublicKey) -> str:
    """``SHA256:<base64, unpadded>`` of the key's OpenSSH wire form: what ``ssh-keygen -l`` prints."""
    line = key.public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    blob = base64.b64decode(line.split()[1])
    return "SHA256:" + base64.b64encode(hashlib.sha256(blob).digest()).decode().rstrip("=")


def signed_payload(header: str, data_sha256: str) -> bytes:
    """The bytes a signature covers: the domain tag, the header's length and text, the weights' SHA-256."""
    text = header.encode()
    return DOMAIN + struct.pack(">Q", len(text)) + text + bytes.fromhex(data_sha256)


def sha256_hex(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@dataclass(frozen=True)
class Signature:
    key: str
    """the signing key's fingerprint"""
    value: bytes

    @property
    def label(self) -> str:
        return json.dumps(
            {"signature": ALGORITHM, "key": self.key, "value": base64.b64encode(self.value).decode()},
            sort_keys=True,
        )

    @classmethod
    def parse(cls, label: str) -> Signature:
        """The signature in a label; raises ``SignatureError`` (``signature_malformed``) with the reason."""
        if len(label) > MAX_SIGNATURE_CHARS:
            raise SignatureError("signature_malformed", f"signature field of {len(label)} characters, more than "
                                 f"{MAX_SIGNATURE_CHARS}")  # fmt: skip
        if not label:
            raise SignatureError("signature_malformed", "empty signature field")
        try:
            obj = json.loads(label)
        except ValueError:
            raise SignatureError("signature_malformed", "signature field is not JSON") from None
        if not isinstance(obj, dict) or obj.get("signature") != ALGORITHM:
            raise SignatureError("signature_malformed", f'signature field is not a {{"signature": "{ALGORITHM}"}} '
                                 "object")  # fmt: skip
        key, value = obj.get("key"), obj.get("value")
        if not isinstance(key, str) or not key.startswith("SHA256:"):
            raise SignatureError("signature_malformed", "signature names no key fingerprint (SHA256:...)")
        if not isinstance(value, str):
            raise SignatureError("signature_malformed", "signature has no value")
        try:
            raw = base64.b64decode(value, validate=True)
        except (binascii.Error, ValueError):
            raise SignatureError("signature_malformed", "signature value is not base64") from None
        if len(raw) != _SIGNATURE_BYTES:
            raise SignatureError("signature_malformed", f"signature of {len(raw)} bytes, Ed25519's are "
                                 f"{_SIGNATURE_BYTES}")  # fmt: skip
        return cls(key, raw)


class Signer:
    """A private key that signs weights (the trainer's)."""

    def __init__(self, key: Ed25519PrivateKey, source: str = ""):
        self._key = key
        self.fingerprint = fingerprint(key.public_key())
        self.source = source

    def sign(self, header: str, data_sha256: str) -> Signature:
        return Signature(self.fingerprint, self._key.sign(signed_payload(header, data_sha256)))

    @property
    def public_key(self) -> Ed25519PublicKey:
        return self._key.public_key()


@dataclass(frozen=True)
class TrustedKey:
    key: Ed25519PublicKey
    fingerprint: str
    source: str
    """the file it came from"""


class TrustedKeys:
    """The public keys a policy node takes weights from, by fingerprint."""

    def __init__(self, keys: list[TrustedKey] | None = None):
        self.keys = {k.fingerprint: k for k in keys or []}

    def __bool__(self) -> bool:
        return bool(self.keys)

    def verify(self, header: str, data_sha256: str, label: str | None) -> str:
        """The fingerprint of the trusted key whose signature ``label`` is over (header, weights); raises
        ``SignatureError`` when it is missing, malformed, by a key not trusted, or not over these bytes."""
        if label is None:
            raise SignatureError("unsigned", "the weights are not signed")
        signature = Signature.parse(label)
        trusted = self.keys.get(signature.key)
        if trusted is None:
            raise SignatureError("untrusted_key", f"signed by {signature.key}, not a trusted key")
        try:
            trusted.key.verify(signature.value, signed_payload(header, data_sha256))
        except InvalidSignature:
            raise SignatureError("bad_signature", f"the signature by {signature.key} does not match the "
                                 "message (altered, or signed for other weights)") from None  # fmt: skip
        return signature.key


# -- key files ---------------------------------------------------------------------------------------------------
def _read_key_file(path: Path) -> bytes:
    try:
        if path.stat().st_size > MAX_KEY_FILE_BYTES:
            raise KeyFileError(path, f"larger than {MAX_KEY_FILE_BYTES} bytes: not a key file")
        return path.read_bytes()
    except FileNotFoundError:
        raise KeyFileError(path, "no such file") from None
    except OSError as err:
        raise KeyFileError(path, f"cannot read it ({err.strerror or err})") from None


def _is_private(data: bytes) -> bool:
    return b"PRIVATE KEY-----" in data


def load_public_key(path: str | Path) -> TrustedKey:
    """An Ed25519 public key file (OpenSSH one-line or PEM); raises ``KeyFileError`` naming the file and the
    reason (missing, unreadable, not a key, a private key, another algorithm)."""
    path = Path(path)
    data = _read_key_file(path)
    if _is_private(data):
        raise KeyFileError(path, "holds a PRIVATE key; give the public key (.pub): the private key stays with "
                           "the trainer")  # fmt: skip
    try:
        if data.lstrip().startswith(b"-----BEGIN"):
            key = serialization.load_pem_public_key(data)
        else:
            key = serialization.load_ssh_public_key(data.strip())
    except (ValueError, UnsupportedAlgorithm, TypeError) as err:
        raise KeyFileError(path, f"not a public key file ({err})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise KeyFileError(path, f"a {type(key).__name__.removesuffix('PublicKey') or 'non'} key, not Ed25519")
    return TrustedKey(key, fingerprint(key), str(path))


def load_trusted_keys(paths: list[str]) -> tuple[TrustedKeys, list[KeyFileError]]:
    """The keys of every file that holds a usable one, and the error of every file that does not."""
    keys, errors = [], []
    for p in paths:
        try:
            keys.append(load_public_key(p))
        except KeyFileError as err:
            errors.append(err)
    return TrustedKeys(keys), errors


def load_signing_key(path: str | Path) -> Signer:
    """An Ed25519 private key file (OpenSSH or PKCS#8 PEM, unencrypted); raises ``KeyFileError``. A file that
    others can read is refused, as ssh refuses it: a signing key is a robot's controller."""
    path = Path(path)
    data = _read_key_file(path)
    if not _is_private(data):
        raise KeyFileError(path, "not a private key file (a public .pub key cannot sign)")
    if path.stat().st_mode & 0o077:
        raise KeyFileError(path, f"readable by others (mode {path.stat().st_mode & 0o777:o}); chmod 600 it")
    try:
        if b"OPENSSH PRIVATE KEY" in data:
            key = serialization.load_ssh_private_key(data, password=None)
        else:
            key = serialization.load_pem_private_key(data, password=None)
    except (ValueError, UnsupportedAlgorithm, TypeError) as err:
        raise KeyFileError(path, f"not a usable private key ({err})") from None
    if not isinstance(key, Ed25519PrivateKey):
        raise KeyFileError(path, f"a {type(key).__name__.removesuffix('PrivateKey')} key, not Ed25519")
    return Signer(key, str(path))


def public_key_path(private_path: str | Path) -> Path:
    """Where a key pair's public half lives: ``<private>.pub``, as ssh-keygen puts it."""
    private_path = Path(private_path)
    return private_path.with_name(private_path.name + ".pub")


def write_key_pair(private_path: str | Path, comment: str = "morph-policy-signing", overwrite: bool = False) -> Signer:
    """A new Ed25519 key pair: ``private_path`` (OpenSSH format, mode 0600) and ``<private_path>.pub`` (one
    line ending in the comment and the fingerprint). Refuses to replace an existing key unless asked."""
    private_path = Path(private_path)
    public_path = public_key_path(private_path)
    if not overwrite and (private_path.exists() or public_path.exists()):
        raise FileExistsError(f"{private_path} or its .pub exists already; refusing to replace a key")
    if any(c.isspace() for c in comment):
        raise ValueError(f"the comment must be one word, got {comment!r}")
    key = Ed25519PrivateKey.generate()
    signer = Signer(key, str(private_path))
    private = key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.OpenSSH, serialization.NoEncryption()
    )
    public = key.public_key().public_bytes(serialization.Encoding.OpenSSH, serialization.PublicFormat.OpenSSH)
    atomic_write_bytes(private_path, private, file_mode=0o600)  # set on the file, whatever the umask
    atomic_write_bytes(public_path, public + f" {comment} {signer.fingerprint}\n".encode())
    return signer
