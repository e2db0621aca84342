"""Fixtures shared by the core's tests."""

import numpy as np
import pytest

from morph_core.protocol.transition_batch import TransitionBatch


def _random_trees(batch: TransitionBatch, seed: int = 0) -> TransitionBatch:
    """``batch`` with one random tree per episode (joint j's parent drawn from -1..j-1; -1 at padding),
    nothing else changed."""
    rng = np.random.default_rng(seed)
    parents = np.full(batch.parents.shape, -1, np.int64)
    for e in np.unique(batch.episode):
        rows = np.flatnonzero(batch.episode == e)
        n = int(batch.num_joints[rows[0]])
        parents[rows, :n] = [rng.integers(-1, j) if j else -1 for j in range(n)]
    out = TransitionBatch.from_arrays({**batch.arrays(), "parents": parents})
    assert not out.is_chains
    return out


@pytest.fixture
def random_trees():
    """The function ``_random_trees``: recorded transitions made trees (the data path's tests)."""
    return _random_trees
