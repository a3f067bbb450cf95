"""Who a round waits for: the rules of leaving a neighbour out and taking it back, alone."""

from __future__ import annotations

from swarmmap.services.learner.exchange import ExchangeRules, ExchangeStats
from swarmmap.services.learner.membership import REFUSED_OUT_FOR_GOOD, Membership


def test_a_neighbour_left_out_again_for_refused_states_stays_out(caplog):
    """Left out for sending only refused States, a neighbour comes back with a State that
    passes; left out for it REFUSED_OUT_FOR_GOOD times, it stays out (each return cost the team
    silent_after of waiting)."""
    stats = ExchangeStats()
    m = Membership(0, {1, 2, 3}, ExchangeRules(silent_after=1.0), stats)
    now = 0.0
    for time_out in range(REFUSED_OUT_FOR_GOOD):
        m.progress.heard = dict.fromkeys(m.progress.heard, now)
        m.progress.refused_since[1] = now
        now += 1.5
        m.check({1}, set(), rnd=time_out, now=now)  # (the round waits on 1 alone)
        assert 1 not in m.active
        m.came_back(1, time_out + 1, now_round=True)
        assert (1 in m.active) == (time_out + 1 < REFUSED_OUT_FOR_GOOD)
    assert 1 in m.banned and stats.refused["refused"] == 1 and {2, 3} <= m.active
    assert "for the 2nd time; it is left out for the rest of the run" in caplog.text


def test_silence_is_no_step_forward_and_a_neighbour_that_takes_part_gets_longer():
    """A neighbour not heard (no step forward) for silent_after is left out; once a State of it
    was taken, only after COMPLETE_WAIT x silent_after without its RoundComplete, and after
    NEXT_STATE_WAIT x silent_after without its next State once it completed, whatever round this
    node is at (on a ring, a node that went on to the next round must not leave out the neighbour
    that waits for a silent member of its own, or for one that owes its RoundComplete)."""
    from swarmmap.services.learner.membership import COMPLETE_WAIT, NEXT_STATE_WAIT

    m = Membership(0, {1, 2, 3}, ExchangeRules(silent_after=1.0), ExchangeStats())
    for j in (1, 2, 3):
        m.progress.took_state(j, 0, now=0.0)
    m.progress.completed(3, 0, now=1.0)  # (3 finished round 0: it owes its State of round 1, heard at 1.0)
    m.check({1, 2, 3}, set(), rnd=1, now=1.5)
    assert m.active == {1, 2, 3}
    m.progress.completed(2, 0, now=1.8)
    m.check({1, 2, 3}, set(), rnd=1, now=COMPLETE_WAIT * 1.0 + 0.1)
    assert m.active == {2, 3} and m.refusals_out == {(1, "incomplete"): 1}
    m.check({2, 3}, set(), rnd=1, now=1.0 + NEXT_STATE_WAIT * 1.0 + 0.1)
    assert m.active == {2} and m.refusals_out == {(1, "incomplete"): 1, (3, "silent"): 1}
    assert m.progress.owes == {} and m.progress.between == {2} and m.stats.refused["incomplete"] == 0
    m2 = Membership(0, {1}, ExchangeRules(silent_after=1.0), ExchangeStats())
    m2.progress.heard = {1: 0.0}
    m2.check({1}, set(), rnd=0, now=1.5)
    assert m2.active == set()


def test_a_neighbour_that_sends_states_without_their_round_complete_again_stays_out(caplog):
    """A neighbour taken back by its State of the round at hand whose RoundComplete never comes (a
    far-future or repeating member whose State of a round lands on the round at hand) is left out
    after COMPLETE_WAIT x silent_after; the REFUSED_OUT_FOR_GOOD-th time for good. Silence alone
    (no State) only leaves it out until it speaks again."""
    from swarmmap.services.learner.membership import COMPLETE_WAIT

    stats = ExchangeStats()
    m = Membership(0, {1, 2}, ExchangeRules(silent_after=1.0), stats)
    now = 0.0
    for time_out in range(REFUSED_OUT_FOR_GOOD):
        m.progress.heard = dict.fromkeys(m.progress.heard, now)
        m.progress.took_state(1, 3 * time_out, now)
        now += COMPLETE_WAIT * 1.0 + 0.1
        m.check({1}, set(), rnd=3 * time_out, now=now)
        assert 1 not in m.active
        m.came_back(1, 3 * time_out + 3, now_round=True)
        assert (1 in m.active) == (time_out + 1 < REFUSED_OUT_FOR_GOOD)
    assert 1 in m.banned and stats.refused["incomplete"] == 1 and m.active == {2}
    assert "sent its State of round 3 but no RoundComplete for 2 s, for the 2nd time; it is left out for the rest of the run" in caplog.text
    for _ in range(REFUSED_OUT_FOR_GOOD + 1):  # silent (no State): left out, taken back each time
        m.progress.heard[2] = now
        now += 1.5
        m.check({2}, set(), rnd=9, now=now)
        assert 2 not in m.active
        m.came_back(2, 10, now_round=True)
        assert 2 in m.active


def test_a_neighbour_back_after_a_silence_that_then_owes_its_round_complete_stays_out(caplog):
    """A member silent once (left out, token still there), back with a State of the round at hand
    whose RoundComplete never comes, is left out for good at once: an honest node taken back
    completes the round it sent a State for (a far-future member whose States land on the round at
    hand now and then cost the team a silence each time). Silence alone never bans."""
    from swarmmap.services.learner.membership import COMPLETE_WAIT

    stats = ExchangeStats()
    m = Membership(0, {1, 2}, ExchangeRules(silent_after=1.0), stats)
    m.progress.heard = {1: 0.0, 2: 0.0}
    m.progress.took_state(2, 0, 0.0)
    m.progress.completed(2, 0, 1.2)
    m.check({1, 2}, set(), rnd=0, now=1.5)
    assert m.active == {2} and m.refusals_out == {(1, "silent"): 1}
    m.came_back(1, 34, now_round=True)
    m.progress.took_state(1, 34, 2.0)
    m.check({1}, set(), rnd=34, now=2.0 + COMPLETE_WAIT * 1.0 + 0.1)
    assert 1 in m.banned and stats.refused["incomplete"] == 1
    assert "sent its State of round 34 but no RoundComplete for 2 s, after 1 silence(s) of its own" in caplog.text
