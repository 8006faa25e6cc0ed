"""The back-off helper every link, the forwarder and the supervisor share (no I/O)."""

from __future__ import annotations

import random

import pytest

from drivers.backoff import Backoff


def test_without_jitter_it_doubles_to_the_cap_and_resets() -> None:
    backoff = Backoff(initial_s=0.5, factor=2.0, max_s=2.0, jitter=0.0)
    assert backoff.ready(0.0) and backoff.wait_s(0.0) == 0.0 and backoff.next_attempt_s is None
    delays = [backoff.failed(float(t)) for t in range(6)]
    assert delays == [0.5, 1.0, 2.0, 2.0, 2.0, 2.0]
    assert backoff.failures == 6
    assert backoff.next_attempt_s == 7.0
    assert not backoff.ready(6.9) and backoff.ready(7.0)
    assert backoff.wait_s(6.5) == pytest.approx(0.5)
    backoff.reset()
    assert backoff.ready(0.0) and backoff.failures == 0
    assert backoff.failed(100.0) == 0.5  # after a success it starts over


def test_jitter_stays_within_its_bounds_and_never_exceeds_the_cap() -> None:
    backoff = Backoff(initial_s=0.5, factor=2.0, max_s=2.0, jitter=0.2, rng=random.Random(7))
    delays = []
    for _ in range(200):
        steps = [0.5, 1.0] + [2.0] * 8
        for step in steps:
            delay = backoff.failed(0.0)
            assert 0.8 * step <= delay <= step
            delays.append(delay)
        backoff.reset()
    assert max(delays) <= 2.0
    assert min(delays) >= 0.4  # never zero: a dead peer must not become a busy loop
    capped = [d for d in delays if d > 1.0]
    assert max(capped) - min(capped) > 0.3  # the delays really are spread


def test_the_same_seed_gives_the_same_delays() -> None:
    first = Backoff(rng=random.Random(3))
    second = Backoff(rng=random.Random(3))
    assert [first.failed(0.0) for _ in range(5)] == [second.failed(0.0) for _ in range(5)]


def test_default_link_pacing_sees_a_returning_peer_within_two_seconds() -> None:
    """The link defaults: however long the outage, no wait exceeds 2 s."""
    backoff = Backoff()
    now = 0.0
    while now < 20.0:  # a 20 s outage, one attempt whenever the back-off allows
        now += backoff.failed(now)
    assert backoff.max_s == 2.0
    assert backoff.wait_s(20.0) <= 2.0


@pytest.mark.parametrize(
    "bad",
    [
        {"initial_s": 0.0},
        {"initial_s": -1.0},
        {"factor": 0.5},
        {"initial_s": 2.0, "max_s": 1.0},
        {"jitter": 1.0},
        {"jitter": -0.1},
    ],
)
def test_settings_that_would_busy_loop_or_shrink_are_refused(bad: dict) -> None:
    with pytest.raises(ValueError):
        Backoff(**bad)
