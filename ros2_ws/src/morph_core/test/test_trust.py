"""Signing keys and signatures (``protocol.trust``): key files as OpenSSH writes and reads them, every bad key file
and every bad signature refused with its reason."""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess

import numpy as np
import pytest
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey

from morph_core.protocol.trust import (
    MAX_SIGNATURE_CHARS,
    KeyFileError,
    Signature,
    SignatureError,
    TrustedKeys,
    load_public_key,
    load_signing_key,
    load_trusted_keys,
    public_key_path,
    sha256_hex,
    write_key_pair,
)

HEADER = '{"format": "morph_policy_weights/1", "version": 3}'
DIGEST = sha256_hex(b"weights")


def test_a_new_key_pair_is_private_0600_and_its_public_half_names_the_fingerprint(tmp_path):
    signer = write_key_pair(tmp_path / "keys" / "trainer")
    private, public = tmp_path / "keys" / "trainer", tmp_path / "keys" / "trainer.pub"
    assert public_key_path(private) == public
    assert private.stat().st_mode & 0o777 == 0o600
    assert private.read_bytes().startswith(b"-----BEGIN OPENSSH PRIVATE KEY-----")
    line = public.read_text().split()
    assert line[0] == "ssh-ed25519" and line[-1] == signer.fingerprint
    assert load_public_key(public).fingerprint == signer.fingerprint == load_signing_key(private).fingerprint
    with pytest.raises(FileExistsError):
        write_key_pair(private)  # a key is never replaced by accident
    other = write_key_pair(private, overwrite=True)
    assert other.fingerprint != signer.fingerprint


@pytest.mark.skipif(shutil.which("ssh-keygen") is None, reason="no ssh-keygen on this machine")
def test_keys_are_openssh_keys_both_ways(tmp_path):
    signer = write_key_pair(tmp_path / "ours")
    shown = subprocess.run(["ssh-keygen", "-lf", str(tmp_path / "ours.pub")], capture_output=True, text=True)
    assert shown.returncode == 0 and shown.stdout.split()[1] == signer.fingerprint
    subprocess.run(["ssh-keygen", "-q", "-t", "ed25519", "-N", "", "-C", "theirs", "-f", str(tmp_path / "theirs")],
                   check=True)  # fmt: skip
    theirs = load_signing_key(tmp_path / "theirs")
    assert load_public_key(tmp_path / "theirs.pub").fingerprint == theirs.fingerprint
    label = theirs.sign(HEADER, DIGEST).label
    keys, errors = load_trusted_keys([str(tmp_path / "theirs.pub")])
    assert not errors and keys.verify(HEADER, DIGEST, label) == theirs.fingerprint


def test_pem_keys_are_read_too(tmp_path):
    key = Ed25519PrivateKey.generate()
    (tmp_path / "k.pem").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    os.chmod(tmp_path / "k.pem", 0o600)
    (tmp_path / "k.pub.pem").write_bytes(
        key.public_key().public_bytes(serialization.Encoding.PEM, serialization.PublicFormat.SubjectPublicKeyInfo)
    )
    assert load_signing_key(tmp_path / "k.pem").fingerprint == load_public_key(tmp_path / "k.pub.pem").fingerprint


def _bad_public_key_files(tmp_path) -> dict:
    signer = write_key_pair(tmp_path / "good")
    ecdsa = ec.generate_private_key(ec.SECP256R1()).public_key()
    files = {
        "missing": (tmp_path / "nope.pub", None, "no such file"),
        "empty": (tmp_path / "empty.pub", b"", "not a public key"),
        "garbage": (tmp_path / "garbage.pub", b"hello world\n", "not a public key"),
        "truncated": (tmp_path / "cut.pub", (tmp_path / "good.pub").read_bytes()[:30], "not a public key"),
        "private": (tmp_path / "private.pub", (tmp_path / "good").read_bytes(), "PRIVATE key"),
        "ecdsa": (tmp_path / "ecdsa.pub", ecdsa.public_bytes(serialization.Encoding.OpenSSH,
                                                             serialization.PublicFormat.OpenSSH), "not Ed25519"),
        "huge": (tmp_path / "huge.pub", b"ssh-ed25519 " + b"A" * 100_000, "larger than"),
        "directory": (tmp_path / "adir", "dir", "cannot read"),
    }  # fmt: skip
    for path, content, _ in files.values():
        if content == "dir":
            path.mkdir()
        elif content is not None:
            path.write_bytes(content)
    return {"signer": signer, **files}


def test_every_bad_trusted_key_file_is_refused_with_its_reason_and_the_good_ones_kept(tmp_path):
    cases = _bad_public_key_files(tmp_path)
    signer = cases.pop("signer")
    for case, (path, _, words) in cases.items():
        with pytest.raises(KeyFileError) as info:
            load_public_key(path)
        assert words in str(info.value) and str(path) in str(info.value) and "\n" not in str(info.value), case
    keys, errors = load_trusted_keys([str(p) for p, _, _ in cases.values()] + [str(tmp_path / "good.pub")])
    assert len(errors) == len(cases) and list(keys.keys) == [signer.fingerprint]


def test_a_signing_key_must_be_private_and_not_readable_by_others(tmp_path):
    write_key_pair(tmp_path / "k")
    with pytest.raises(KeyFileError, match="cannot sign"):
        load_signing_key(tmp_path / "k.pub")
    os.chmod(tmp_path / "k", 0o644)
    with pytest.raises(KeyFileError, match="readable by others"):
        load_signing_key(tmp_path / "k")
    with pytest.raises(KeyFileError, match="no such file"):
        load_signing_key(tmp_path / "missing")


def test_a_signature_verifies_only_for_its_key_header_and_bytes(tmp_path):
    a, b = write_key_pair(tmp_path / "a"), write_key_pair(tmp_path / "b")
    keys = TrustedKeys([load_public_key(tmp_path / "a.pub")])
    label = a.sign(HEADER, DIGEST).label
    assert keys.verify(HEADER, DIGEST, label) == a.fingerprint
    cases = {
        "unsigned": (HEADER, DIGEST, None),
        "untrusted_key": (HEADER, DIGEST, b.sign(HEADER, DIGEST).label),
        "bad_signature": (HEADER.replace("3", "4"), DIGEST, label),
        "bad_signature ": (HEADER, sha256_hex(b"weightz"), label),
    }
    for reason, (header, digest, sig) in cases.items():
        with pytest.raises(SignatureError) as info:
            keys.verify(header, digest, sig)
        assert info.value.reason == reason.strip(), reason
    assert not TrustedKeys() and keys


def _forged(label: str, **over) -> str:
    obj = json.loads(label)
    obj.update(over)
    return json.dumps(obj)


def test_malformed_signature_fields_are_refused_before_any_verification(tmp_path):
    a = write_key_pair(tmp_path / "a")
    keys = TrustedKeys([load_public_key(tmp_path / "a.pub")])
    good = a.sign(HEADER, DIGEST).label
    bad = {
        "empty": "",
        "1 MB": "A" * 1_000_000,
        "just over the limit": " " * (MAX_SIGNATURE_CHARS + 1),
        "not JSON": "ed25519:abc",
        "JSON list": "[1, 2]",
        "other algorithm": _forged(good, signature="rsa"),
        "no key": _forged(good, key=None),
        "key not a fingerprint": _forged(good, key="alice"),
        "not base64": _forged(good, value="@@@not base64@@@"),
        "value a number": _forged(good, value=12),
        "short": _forged(good, value=base64.b64encode(b"x" * 10).decode()),
    }
    for case, label in bad.items():
        with pytest.raises(SignatureError) as info:
            keys.verify(HEADER, DIGEST, label)
        assert info.value.reason == "signature_malformed" and str(info.value), case


def test_fuzzed_signature_fields_are_always_refused_with_a_known_reason(tmp_path):
    a = write_key_pair(tmp_path / "a")
    keys = TrustedKeys([load_public_key(tmp_path / "a.pub")])
    good = a.sign(HEADER, DIGEST).label
    rng = np.random.default_rng(0)
    reasons = set()
    for i in range(3000):
        kind = i % 4
        if kind == 0:  # random bytes as text
            label = rng.integers(0, 256, rng.integers(0, 300)).astype(np.uint8).tobytes().decode("latin-1")
        elif kind == 1:  # the good label with characters flipped
            chars = list(good)
            for k in rng.integers(0, len(chars), rng.integers(1, 4)):
                chars[k] = chr(int(rng.integers(32, 127)))
            label = "".join(chars)
        elif kind == 2:  # a well-formed signature of random bytes
            label = Signature(a.fingerprint, rng.integers(0, 256, 64).astype(np.uint8).tobytes()).label
        else:  # the good label cut short
            label = good[: rng.integers(0, len(good))]
        if label == good:
            continue
        with pytest.raises(SignatureError) as info:
            keys.verify(HEADER, DIGEST, label)
        reasons.add(info.value.reason)
    assert reasons <= {"signature_malformed", "untrusted_key", "bad_signature"}
    assert {"signature_malformed", "bad_signature"} <= reasons
