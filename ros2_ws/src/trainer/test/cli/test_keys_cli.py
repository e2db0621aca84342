"""``morph-keys``: a key pair made, a checkpoint signed and checked, and every mistake one line and exit 1."""

from __future__ import annotations

import json

import torch

from morph_core.policy.actor_critic import GraphActorCritic
from morph_core.policy.weights import load_checkpoint
from morph_core.protocol.trust import load_public_key
from trainer.cli.keys import main


def test_new_sign_check_and_every_mistake_refused(tmp_path, capsys):
    key = tmp_path / "keys" / "trainer"
    assert main(["new", str(key)]) == 0
    fingerprint = load_public_key(f"{key}.pub").fingerprint
    out = capsys.readouterr().out
    assert fingerprint in out and "--signing-key" in out and "trusted_keys:=" in out
    assert key.stat().st_mode & 0o777 == 0o600
    assert main(["new", str(key)]) == 1 and "refusing to replace" in capsys.readouterr().err

    torch.manual_seed(0)
    checkpoint = tmp_path / "p.safetensors"
    GraphActorCritic().save(checkpoint, metadata={"version": 7, "note": "kept"})
    data = checkpoint.read_bytes()
    assert main(["check", str(checkpoint)]) == 0 and "unsigned" in capsys.readouterr().out
    assert main(["sign", str(checkpoint), "--key", str(key)]) == 0
    assert checkpoint.read_bytes() == data  # only the .json changes
    meta = json.loads(checkpoint.with_suffix(".json").read_text())
    assert meta["metadata"] == {"version": 7, "note": "kept"} and load_checkpoint(checkpoint).signed is not None
    assert main(["check", str(checkpoint), "--trusted", f"{key}.pub"]) == 0
    assert f"signed by {fingerprint} (trusted), version 7" in capsys.readouterr().out
    assert main(["check", str(checkpoint)]) == 0 and "not a trusted key" in capsys.readouterr().out

    tampered = bytearray(data)
    tampered[-3] ^= 1
    checkpoint.write_bytes(bytes(tampered))
    assert main(["check", str(checkpoint), "--trusted", f"{key}.pub"]) == 1
    assert "does not match the file" in capsys.readouterr().err
    for argv, words in (
        (["check", str(checkpoint), "--trusted", str(key)], "PRIVATE key"),  # the private half by mistake
        (["sign", str(checkpoint), "--key", f"{key}.pub"], "cannot sign"),
        (["sign", str(tmp_path / "missing.safetensors"), "--key", str(key)], "no such file"),
        (["sign", str(checkpoint), "--key", str(key), "--version", "-1"], "version must be"),
    ):
        assert main(argv) == 1, argv
        err = capsys.readouterr().err
        assert words in err and err.count("\n") == 1, (argv, err)
