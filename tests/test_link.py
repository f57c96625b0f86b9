"""The delayed ground link: frames up and states down arrive a delay late."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from payload.teleop.link import DelayedLink, DelayLine, LinkError, parse_link_delay

DT = 0.02


@dataclass(frozen=True)
class _View:
    t: float
    sent: float


@dataclass(frozen=True)
class _Frame:
    stamp: float
    seen: float | None  # when the state the operator acted on was sent


class _Operator:
    """Makes one frame per call, naming the state it saw."""

    finished = False

    def frame(self, t, world):
        return _Frame(100.0 + t, None if world is None else world.sent)


def test_parse_link_delay():
    assert parse_link_delay("1") == (1.0, 0.0)
    assert parse_link_delay("0.5:0.1") == (0.5, 0.1)
    for bad in ("x", "1:2:3", "-1", "0.1:0.2", "nan", ""):
        with pytest.raises(LinkError, match="--link-delay"):
            parse_link_delay(bad)


def test_delay_line_holds_the_newest_arrived():
    line = DelayLine(0.1, 0.0, np.random.default_rng(0))
    line.put(0.0, "a")
    assert line.take(0.0) == "a"  # the first item is there from the start
    line.put(0.05, "b")
    assert line.take(0.1) == "a"  # "a" arrived at 0.1, "b" not yet
    assert line.take(0.149) == "a"
    assert line.take(0.15) == "b"


def test_jitter_never_delivers_an_older_item_after_a_newer_one():
    rng = np.random.default_rng(3)
    line = DelayLine(0.2, 0.15, rng)
    got = []
    for k in range(400):
        line.put(k * DT, k)
        got.append(line.take(k * DT))
    assert got == sorted(got)
    lags = [k - v for k, v in enumerate(got) if k > 30]
    assert min(lags) * DT >= 0.05 - 1e-9 and max(lags) * DT <= 0.35 + DT


@pytest.mark.parametrize("delay", [0.5, 1.0])
def test_delayed_link_delays_both_ways(delay):
    link = DelayedLink(_Operator(), delay)
    n = round(delay / DT)
    for k in range(200):
        t = k * DT
        fr = link.frame(t, _View(t, t))
        assert fr.stamp == pytest.approx(100.0 + t)  # restamped on the robot's clock
        if k >= 2 * n:
            # the robot holds the frame made a delay ago, made from the state sent a
            # delay before that
            assert fr.seen == pytest.approx(t - 2 * delay)
