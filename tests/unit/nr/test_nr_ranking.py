"""The lazy PF ranking the cell uses gives the order of the full sort, ties and classes included."""

from __future__ import annotations

import random

from netsim.nr.scheduler import ProportionalFair


def test_ranked_follows_order_with_ties_priorities_and_urgency() -> None:
    rnd = random.Random(7)
    for trial in range(300):
        n = rnd.randint(1, 12)
        pf = ProportionalFair(n, 0.98)
        for slot in range(rnd.randint(0, 40)):
            u = rnd.randrange(n)
            if rnd.random() < 0.7:
                pf.served(u, rnd.choice([0, 1000, 2000]), slot)
        slot = 41 + rnd.randint(0, 400)  # decay gaps beyond the table of powers too
        candidates = rnd.sample(range(n), rnd.randint(0, n))
        # Few distinct values: equal metrics (ties broken by UE index) happen often.
        rate = [rnd.choice([100.0, 200.0, 300.0]) for _ in range(n)]
        priority = [10] * n if trial % 2 else [rnd.choice([1, 10]) for _ in range(n)]
        urgency = None if trial % 3 == 0 else [rnd.choice([1.0, 2.0]) for _ in range(n)]
        expected = pf.order(candidates, priority, rate, slot, urgency)
        assert list(pf.ranked(candidates, priority, rate, slot, urgency)) == expected
