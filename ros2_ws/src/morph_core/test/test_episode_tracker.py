"""EpisodeTracker: which acted-on states begin an announced episode, whichever of the two arrives first."""

from morph_core.protocol.episode_tracker import EpisodeTracker

P = 40


def test_announcement_before_its_state():
    t = EpisodeTracker()
    assert not t.state(0) and not t.state(P)
    assert not t.announced(2 * P)
    assert t.state(2 * P)  # the announced episode's first state
    assert not t.state(3 * P)
    assert not t.announced(2 * P)  # a repeat


def test_announcement_after_its_state():
    t = EpisodeTracker()
    for k in range(3):
        t.state(k * P)
    assert t.announced(2 * P)  # late: restart now
    assert not t.state(3 * P)  # and not again at the next state
    assert not t.announced(2 * P)


def test_an_announcement_of_an_older_episode_changes_nothing():
    t = EpisodeTracker()
    t.announced(0)
    assert t.state(0)
    t.announced(5 * P)
    for k in range(1, 8):
        t.state(k * P)
    assert not t.announced(0) and not t.announced(5 * P)


def test_a_skipped_first_state_restarts_at_the_next_state():
    t = EpisodeTracker()
    t.state(0)
    t.announced(2 * P)
    assert t.state(3 * P)  # the episode's first state was lost: restart with the first one seen


def test_a_stamp_going_back_is_a_new_stream():
    t = EpisodeTracker()
    t.announced(0)
    t.state(0)
    for k in range(1, 50):
        t.state(k * P)
    assert not t.announced(0)  # the restarted sim's announcement looks like an old one ...
    assert t.state(0)  # ... but its first state goes back in time
    assert not t.state(P)
    assert not t.announced(2 * P) and t.state(2 * P)  # and its next episodes are followed
