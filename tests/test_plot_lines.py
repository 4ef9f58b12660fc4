"""The lines a run's plots draw: at most PLOT_POINTS points, keeping what a reader looks for (`envelope`,
`thinned` in flightstack.analysis.report)."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from flightstack.analysis.report import PLOT_POINTS, envelope, thinned


# ---------------------------------------------------------------------------------------------- envelope
@pytest.mark.parametrize("n", [1, 7, PLOT_POINTS, PLOT_POINTS + 1, 20_000, 123_457])
def test_envelope_keeps_every_extreme_in_time_order(n: int) -> None:
    rng = np.random.default_rng(n)
    t = np.cumsum(rng.uniform(0.001, 0.003, n))
    y = rng.lognormal(size=n)
    spike = int(rng.integers(n))
    y[spike] = 1e6  # one sample far above the rest must stay drawn
    tt, yy = envelope(t, y)
    if n <= PLOT_POINTS:
        assert tt is t and yy is y
        return
    assert len(tt) <= PLOT_POINTS
    kept = np.searchsorted(t, tt)  # a subsequence of the samples, in time order
    assert np.array_equal(t[kept], tt) and np.array_equal(y[kept], yy) and np.all(np.diff(kept) > 0)
    assert yy.max() == y.max() == 1e6 and yy.min() == y.min()
    # independent check: every sample lies inside the [min, max] of the kept samples of its bucket
    edges = np.linspace(0, n, PLOT_POINTS // 2 + 1).astype(int)
    for i0, i1 in itertools.pairwise(edges):
        inside = (kept >= i0) & (kept < i1)
        assert inside.sum() == 2
        assert yy[inside].min() == y[i0:i1].min() and yy[inside].max() == y[i0:i1].max()


@pytest.mark.parametrize("n", [1, 5, PLOT_POINTS, PLOT_POINTS + 1, 20_000, 20_001])
def test_thinned_keeps_both_ends_within_the_budget(n: int) -> None:
    xy = np.column_stack([np.arange(n), -np.arange(n)]).astype(float)
    out = thinned(xy)
    assert len(out) <= PLOT_POINTS + 1
    assert np.array_equal(out[0], xy[0]) and np.array_equal(out[-1], xy[-1])
    step = np.diff(out[:-1, 0])
    assert len(set(step)) <= 1  # one stride (the last row may come sooner)
    if n <= PLOT_POINTS:
        assert out is xy
