"""The weights message layout: a real policy's safetensors + config round trip, every bad input refused by name."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest
import torch
from safetensors.numpy import save as np_save
from safetensors.torch import save as torch_save

from morph_core.msgs.policy_weights import (
    DATA_LABEL,
    MAX_WEIGHTS_BYTES,
    PolicyWeightsError,
    pack_policy_weights,
    parse_policy_version,
    policy_version_frame_id,
    unpack_policy_weights,
)
from morph_core.policy.actor_critic import GraphActorCritic


@pytest.fixture(scope="module")
def policy():
    torch.manual_seed(5)
    return GraphActorCritic()


def _data(policy) -> bytes:
    return torch_save({k: v.detach().contiguous() for k, v in policy.state_dict().items()})


def _fields(dims):
    return [d[0] for d in dims], [d[1] for d in dims]


def test_round_trip_keeps_every_tensor_and_the_config(policy):
    config = asdict(policy.config)
    dims, data = pack_policy_weights(7, config, _data(policy), {"run": "abc"})
    w = unpack_policy_weights(*_fields(dims), data)
    assert (w.version, w.config, w.metadata) == (7, config, {"run": "abc"})
    state = policy.state_dict()
    assert set(w.tensors) == set(state)
    for k, v in state.items():
        np.testing.assert_array_equal(w.tensors[k], v.detach().numpy())
    assert dims[0] == (DATA_LABEL, len(data), len(data))


def _header(**over):
    h = {"format": "morph_policy_weights/1", "version": 1, "policy": {}, "metadata": {}}
    h.update(over)
    return json.dumps(h)


@pytest.mark.parametrize(
    ("labels", "sizes", "data", "match"),
    [
        (["safetensors"], [96], None, "2 or 3 layout dimensions"),
        (["weights", _header()], [96, 0], None, "labelled 'safetensors'"),
        (["safetensors", _header()], [95, 0], None, "layout says 95 bytes"),
        (["safetensors", "{not json"], [96, 0], None, "not JSON"),
        (["safetensors", json.dumps({"version": 1})], [96, 0], None, "not a morph_policy_weights/1"),
        (["safetensors", _header(version=-1)], [96, 0], None, "version must be"),
        (["safetensors", _header(version=True)], [96, 0], None, "version must be"),
        (["safetensors", _header(version="3")], [96, 0], None, "version must be"),
        (["safetensors", _header(version=2**63)], [96, 0], None, "version must be"),
        (["safetensors", _header(epoch=-5)], [96, 0], None, "epoch must be"),
        (["safetensors", _header(epoch=1.5)], [96, 0], None, "epoch must be"),
        (["safetensors", _header(), "sig", "more"], [96, 0, 0, 0], None, "2 or 3 layout dimensions"),
        (["safetensors", _header(policy=[1])], [96, 0], None, "must be JSON objects"),
        (["safetensors", _header()], [10, 0], b"0123456789", "not a safetensors file"),
    ],
)
def test_bad_layouts_are_refused_with_the_reason(labels, sizes, data, match):
    good = np_save({"w": np.zeros((2, 3), np.float32)})
    assert len(good) == 96
    with pytest.raises(PolicyWeightsError, match=match):
        unpack_policy_weights(labels, sizes, good if data is None else data)


@pytest.mark.parametrize(
    ("tensors", "match"),
    [
        ({"w": np.array([1.0, np.nan], np.float32)}, "NaN or inf in tensor 'w'"),
        ({"w": np.array([np.inf], np.float64)}, "NaN or inf"),
        ({"w": np.array([1, 2], np.int64)}, "expected floats"),
        ({}, "holds no tensor"),
    ],
)
def test_bad_tensors_are_refused(tensors, match):
    data = np_save(tensors)
    with pytest.raises(PolicyWeightsError, match=match):
        unpack_policy_weights(["safetensors", _header()], [len(data), 0], data)


def test_pack_refuses_what_a_node_would_refuse():
    data = np_save({"w": np.array([np.nan], np.float32)})
    with pytest.raises(PolicyWeightsError, match="NaN"):
        pack_policy_weights(1, {}, data)
    with pytest.raises(PolicyWeightsError, match="version"):
        pack_policy_weights(-2, {}, np_save({"w": np.zeros(1, np.float32)}))


def test_oversized_payload_refused_before_parsing():
    big = bytes(MAX_WEIGHTS_BYTES + 1)
    with pytest.raises(PolicyWeightsError, match="more than the limit"):
        unpack_policy_weights(["safetensors", _header()], [len(big), 0], big)


def test_version_frame_id_round_trip():
    for v in (0, 1, 12345):
        assert parse_policy_version(policy_version_frame_id(v)) == v
    assert policy_version_frame_id(None) == ""
    for bad in ("", "odom", "weights@", "weights@-1", "weights@1x", "xweights@1"):
        assert parse_policy_version(bad) is None
