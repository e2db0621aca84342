"""policy_info layout and answer tags: the plain-array halves of two message conventions."""

import math

import numpy as np
import pytest
import torch

from morph_core.msgs.policy_info import PolicyInfoError, pack_policy_info, unpack_policy_info
from morph_core.msgs.stamps import answer_tag, from_ns, parse_answer_tag, seconds_to_ns, to_ns
from morph_core.policy.actor_critic import gaussian_log_prob


def test_policy_info_round_trip_and_log_prob():
    a, mu, log_std = np.array([0.3, -1.2, 2.0]), np.array([0.1, 0.0, 1.5]), -0.3
    fields = pack_policy_info(a, mu, log_std)
    rec = unpack_policy_info(7, 40_000_000, ["j1", "j2", "j3"], **fields)
    np.testing.assert_array_equal(rec.action, a)
    np.testing.assert_array_equal(rec.mean, mu)
    np.testing.assert_array_equal(rec.log_std, [log_std] * 3)
    torch_lp = gaussian_log_prob(
        torch.tensor(a)[None], torch.tensor(mu)[None], torch.tensor(log_std, dtype=torch.float64), torch.ones(1, 3)
    )
    assert rec.log_prob == pytest.approx(float(torch_lp), abs=1e-12)
    # by hand, first joint: z = 0.2 / exp(-0.3)
    z = 0.2 / math.exp(-0.3)
    assert rec.log_prob_per_joint[0] == pytest.approx(-0.5 * z * z + 0.3 - 0.5 * math.log(2 * math.pi))


@pytest.mark.parametrize(
    "fields",
    [
        {"positions": [0.0], "velocities": [0.0, 0.0], "accelerations": [0.0, 0.0], "effort": [0.0, 0.0]},
        {"positions": [0.0, math.nan], "velocities": [0.0, 0.0], "accelerations": [0.0, 0.0], "effort": [0.0, 0.0]},
        {"positions": [0.0, 0.0], "velocities": [0.0, 0.0], "accelerations": [], "effort": [0.0, 0.0]},
    ],
)
def test_policy_info_rejects_bad_layouts(fields):
    with pytest.raises(PolicyInfoError):
        unpack_policy_info(0, 0, ["a", "b"], **fields)


def test_answer_tags_and_stamps():
    ns = seconds_to_ns(12.04)
    assert ns == 12_040_000_000 and from_ns(ns) == (12, 40_000_000) and to_ns(12, 40_000_000) == ns
    tag = answer_tag(*from_ns(ns))
    assert tag == "joints@12.040000000"
    assert parse_answer_tag(tag) == ns
    for bad in ("", "joints", "joints@1.5", "joints@x.000000000", "joints@1.0000000001", "effort@1.000000000"):
        assert parse_answer_tag(bad) is None
