"""The training points a learner keeps: offline every scan's until the traversal ends, online only
the window's newest scans (memory bounded by the window, not by the traversal)."""

from __future__ import annotations

import numpy as np

from swarmmap.services.learner.collector import Collector
from swarmmap.shared.wire.protocol import Samples, Tensor


def samples(seq: int, last: bool = False, leg: int | None = None, leg_end: bool = False) -> Samples:
    points = np.full((10, 2), seq, np.float32)
    return Samples(run="r", sender=0, seq=seq, t=0.1 * seq, position=[0.0, 0.0], points=Tensor.of(points, "<f4"),
                   labels=Tensor.of(np.zeros(10, np.float32), "<f4"), last=last, leg=leg, leg_end=leg_end)


def test_online_keeps_only_the_window_and_offline_every_scan():
    online, offline = Collector(keep=50), Collector()
    for seq in range(1000):
        online.add(samples(seq))
        offline.add(samples(seq))
    assert len(online.points) == 50 and len(offline.points) == 1000
    points, labels = online.arrays(50)
    assert points.shape == (500, 2) and points[0, 0] == 950 and points[-1, 0] == 999
    assert online.arrays(5)[0][0, 0] == 995
    assert offline.arrays()[0].shape == (10_000, 2)


def test_a_restarted_worlds_scans_are_taken_once():
    """A world restarted mid-traversal drives it again from scan 0: the scans the learner has are
    dropped and counted, the new ones taken, and the points are a clean traversal's."""
    clean, restarted = Collector(), Collector()
    for seq in range(100):
        clean.add(samples(seq, last=seq == 99))
    for seq in [*range(40), *range(100)]:
        restarted.add(samples(seq, last=seq == 99))
    assert restarted.repeated == 40 and restarted.done.is_set()
    np.testing.assert_array_equal(restarted.arrays()[0], clean.arrays()[0])


def test_an_exploring_learner_waits_for_its_legs_end_and_trains_on_the_legs_driven_so_far():
    """Leg 0 is one scan; a leg's last scan says so. Scans of later legs (a world ahead of the
    learner) stay out of the points of a leg before them, whenever they came."""
    import threading

    c, stop = Collector(keep=100), threading.Event()
    c.add(samples(0, leg=0, leg_end=True))
    assert c.wait_leg(0, 0.1, stop) and not c.wait_leg(1, 0.05, stop)
    for seq in range(1, 4):
        c.add(samples(seq, leg=1, leg_end=seq == 3))
    c.add(samples(4, leg=2))
    assert c.wait_leg(1, 0.1, stop) and not c.wait_leg(2, 0.05, stop)
    assert c.arrays(through_leg=0)[0].shape == (10, 2) and c.arrays(through_leg=1)[0][-1, 0] == 3
    assert c.arrays(through_leg=2)[0].shape == (50, 2) and c.arrays(2, through_leg=1)[0][0, 0] == 2
    c.add(samples(5, leg=2, last=True))  # the robot's drive is over: no leg is waited for any more
    assert c.wait_leg(7, 0.05, stop)
