"""lcmodels.stats: each interval and test against values worked out independently."""

import math

import numpy as np
import pytest

from lcmodels.stats import aggregate_scores, mcnemar, normal_interval, t_interval, wilson_interval


def _wilson_by_formula(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


@pytest.mark.parametrize(("k", "n"), [(3, 6), (0, 20), (20, 20), (771, 1000), (1, 2000)])
def test_wilson_matches_the_formula(k, n):
    assert wilson_interval(k, n) == pytest.approx(_wilson_by_formula(k, n), abs=1e-9)
    lo, hi = wilson_interval(k, n)
    assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_wilson_of_nothing_is_nan():
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_t_interval_over_two_seeds_is_wide():
    # 76.5 +- 1.1 (sample sd of two seeds) is not a 95% interval: the t interval over two seeds is about +- 10
    lo, hi = t_interval([0.757, 0.772])
    sem = 0.015 / math.sqrt(2) / math.sqrt(2)  # sample sd of the two, over the square root of two
    assert hi - lo == pytest.approx(2 * 12.7062 * sem, rel=1e-4)  # t(0.975, 1 degree of freedom) = 12.706
    assert lo < 0.70 and hi > 0.83
    assert all(math.isnan(v) for v in t_interval([0.5]))
    assert t_interval([0.4, 0.4, 0.4]) == pytest.approx((0.4, 0.4))


def test_normal_interval_of_the_mean():
    rng = np.random.default_rng(0)
    v = rng.normal(10.0, 2.0, 400)
    lo, hi = normal_interval(v)
    assert lo < v.mean() < hi
    assert hi - lo == pytest.approx(2 * 1.959964 * v.std(ddof=1) / 20, rel=1e-5)


def test_mcnemar_exact():
    a = np.array([True] * 10 + [False] * 2 + [True] * 30 + [False] * 8)
    b = np.array([False] * 10 + [True] * 2 + [True] * 30 + [False] * 8)
    t = mcnemar(a, b)
    assert (t.n, t.only_a, t.only_b) == (50, 10, 2)
    # two-sided exact binomial: 2 * P(X <= 2 | 12, 1/2) = 2 * (1 + 12 + 66) / 4096
    assert t.p_value == pytest.approx(2 * 79 / 4096)
    assert "A beats B" in t.verdict()
    swapped = mcnemar(b, a)
    assert swapped.p_value == pytest.approx(t.p_value) and "B beats A" in swapped.verdict()
    same = mcnemar(a, a)
    assert same.p_value == 1.0 and "no significant difference" in same.verdict()
    with pytest.raises(ValueError, match="same episodes"):
        mcnemar(a, b[:-1])


def test_aggregate_scores_iqm_and_bootstrap():
    scores = np.array([[0.8, 0.9, 0.5, 0.7, 1.0, 0.6, 0.75, 0.85]])
    one = aggregate_scores(scores)
    flat = np.sort(scores.ravel())
    assert one["iqm"]["value"] == pytest.approx(flat[2:6].mean())  # the middle half of 8 values
    assert one["mean"]["value"] == pytest.approx(scores.mean())
    assert one["iqm"]["ci95"] is None  # one run: nothing to resample over runs
    rng = np.random.default_rng(1)
    three = np.clip(scores + rng.normal(0, 0.05, (3, 8)), 0, 1)
    agg = aggregate_scores(three, reps=2000, seed=3)
    for k in ("iqm", "mean"):
        lo, hi = agg[k]["ci95"]
        assert lo <= agg[k]["value"] <= hi and hi - lo < 0.2
        assert agg[k]["runs"] == 3 and agg[k]["scenarios"] == 8
    np.random.seed(11)  # noqa: NPY002
    before = np.random.random()  # noqa: NPY002
    np.random.seed(11)  # noqa: NPY002
    assert aggregate_scores(three, reps=2000, seed=3) == agg  # seeded: the same intervals
    assert np.random.random() == before  # and numpy's global generator left as it was  # noqa: NPY002
    with pytest.raises(ValueError, match="runs, scenarios"):
        aggregate_scores(np.array([0.5, np.nan]))
