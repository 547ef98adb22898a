"""Means and 95 % intervals over seeds, against hand-worked values."""

import math

import numpy as np
import pytest

from lazyq_jax.stats import format_ci, t_interval


def test_two_seeds_by_hand():
    # mean 0.95, sd = 0.1/sqrt(2); t_{0.975, 1} = 12.7062; half = 12.7062 * 0.070711 / sqrt(2)
    out = t_interval([0.9, 1.0])
    assert out["n"] == 2 and math.isclose(out["mean"], 0.95)
    assert math.isclose(out["sd"], 0.1 / math.sqrt(2), rel_tol=1e-12)
    half = 12.7062047 * (0.1 / math.sqrt(2)) / math.sqrt(2)
    assert math.isclose(out["ci95"][0], 0.95 - half, rel_tol=1e-6)
    assert out["ci95"][1] == 1.0  # 0.95 + 0.635 clipped to the rate's upper bound


def test_five_values_unclipped_by_hand():
    # 1..5: mean 3, sd sqrt(2.5); t_{0.975, 4} = 2.776445; half = 2.776445 * 1.581139 / sqrt(5)
    out = t_interval([1, 2, 3, 4, 5], bounds=None)
    half = 2.7764451 * math.sqrt(2.5) / math.sqrt(5)
    np.testing.assert_allclose(out["ci95"], [3 - half, 3 + half], rtol=1e-6)
    wider = t_interval([1, 2, 3, 4, 5], level=0.99, bounds=None)
    assert wider["ci95"][0] < out["ci95"][0] and wider["ci95"][1] > out["ci95"][1]


def test_degenerate_cases():
    assert t_interval([0.7]) == {"mean": 0.7, "ci95": None, "sd": None, "n": 1}
    assert t_interval([0.5, 0.5, 0.5])["ci95"] == [0.5, 0.5]
    assert t_interval([0.0, 0.0])["ci95"] == [0.0, 0.0]
    for bad in ([], [0.5, float("nan")], [[0.1, 0.2]]):
        with pytest.raises(ValueError):
            t_interval(bad)
    with pytest.raises(ValueError, match="level"):
        t_interval([0.1, 0.2], level=95)


def test_format():
    assert format_ci(t_interval([0.9, 1.0])).startswith("95.0 % [31.5, 100.0]")
    assert format_ci(t_interval([0.25])) == "25.0 %"
