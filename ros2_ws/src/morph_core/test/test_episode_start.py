"""The episode announcement's layout: four labelled int64s in, an EpisodeStartRecord out."""

import pytest

from morph_core.msgs.episode_start import (
    LABEL,
    EpisodeCause,
    EpisodeStartError,
    pack_episode_start,
    unpack_episode_start,
)
from morph_core.msgs.records import EpisodeStartRecord


def test_round_trip():
    label, data = pack_episode_start(3, 12_040_000_000, 7, EpisodeCause.STEPS)
    assert label == "episode,stamp_ns,num_joints,cause" == LABEL and data == [3, 12_040_000_000, 7, 1]
    rec = unpack_episode_start(99, label, data)
    assert rec == EpisodeStartRecord(99, 12_040_000_000, 3, 7, "steps")


def test_fields_are_found_by_name():
    rec = unpack_episode_start(0, "stamp_ns,episode", [80_000_000, 2])
    assert (rec.stamp_ns, rec.episode, rec.num_joints, rec.cause) == (80_000_000, 2, None, None)
    rec = unpack_episode_start(0, LABEL + ",extra", [1, 2, 3, 4, 5])  # a later field is ignored
    assert (rec.episode, rec.stamp_ns, rec.num_joints, rec.cause) == (1, 2, 3, "diverged")


@pytest.mark.parametrize(
    "label, data, reason",
    [
        (LABEL, [1, 2, 3], "names 4 fields"),
        ("episode,num_joints", [1, 3], "lacks"),
        ("episode,episode,stamp_ns", [1, 1, 0], "names 3 fields"),
        (LABEL, [-1, 0, 3, 0], "negative"),
        (LABEL, [0, 0, 65, 0], "outside"),
        (LABEL, [0, 0, 3, 9], "unknown cause"),
        ("", [], "names 1 fields"),
    ],
)
def test_bad_announcements_are_refused(label, data, reason):
    with pytest.raises(EpisodeStartError, match=reason):
        unpack_episode_start(0, label, data)
