"""The benchmarks' order statistics."""

from __future__ import annotations

import math

import numpy as np
import pytest

from uniros_async.bench.stats import median_ci


@pytest.mark.parametrize(("n", "ranks"), [(6, (1, 6)), (10, (2, 9)), (29, (9, 21)), (100, (40, 61))])
def test_median_ci_takes_the_ranks_of_the_binomial_tables(n: int, ranks: tuple[int, int]) -> None:
    # 1-based ranks of the 95 % interval, as in the published tables of the sign test's interval
    samples = np.arange(1, n + 1, dtype=float)[::-1]  # unsorted on purpose
    assert median_ci(samples) == (float(ranks[0]), float(ranks[1]))


def test_median_ci_needs_six_samples_at_95_percent() -> None:
    assert all(math.isnan(v) for v in median_ci([1.0, 2.0, 3.0, 4.0, 5.0]))
    assert all(math.isnan(v) for v in median_ci([]))


def test_median_ci_holds_the_median_at_least_as_often_as_it_says() -> None:
    rng = np.random.default_rng(0)
    for n in (12, 60):
        hits = sum(lo <= 0.0 <= hi for lo, hi in (median_ci(rng.standard_cauchy(n)) for _ in range(2000)))
        assert hits / 2000 >= 0.94  # >= 95 % in expectation; 2,000 draws scatter by ~0.5 %
