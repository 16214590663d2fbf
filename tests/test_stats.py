"""Wilson and Newcombe intervals against values computed by hand (and published ones)."""

import math

import pytest

from offline_rl_core.evaluation.stats import excludes_zero, newcombe_diff_ci, wilson_ci


def wilson_by_hand(k, n, z=1.959964):
    p = k / n
    centre = (2 * n * p + z * z) / (2 * (n + z * z))
    half = z * math.sqrt(z * z + 4 * n * p * (1 - p)) / (2 * (n + z * z))
    return centre - half, centre + half


@pytest.mark.parametrize("k,n,expected", [(27, 100, (0.1927, 0.3643)), (3, 100, (0.0103, 0.0845)), (0, 8, (0.0, 0.3244))])
def test_wilson_matches_hand_values(k, n, expected):
    lo, hi = wilson_ci(k, n)
    assert lo == pytest.approx(expected[0], abs=1e-4)
    assert hi == pytest.approx(expected[1], abs=1e-4)
    assert (lo, hi) == pytest.approx(wilson_by_hand(k, n), abs=1e-12)


def test_wilson_edges_stay_in_unit_interval():
    assert wilson_ci(0, 10)[0] == 0.0
    assert wilson_ci(10, 10)[1] == 1.0
    with pytest.raises(ValueError):
        wilson_ci(1, 0)
    with pytest.raises(ValueError):
        wilson_ci(5, 4)


def test_newcombe_chapter_seed0_awac_vs_bc():
    # AWAC 27/100 vs BC 3/100: the chapter reports +0.15..+0.34.
    lo, hi = newcombe_diff_ci(27, 100, 3, 100)
    l1, u1 = wilson_by_hand(27, 100)
    l2, u2 = wilson_by_hand(3, 100)
    assert lo == pytest.approx(0.24 - math.sqrt((0.27 - l1) ** 2 + (u2 - 0.03) ** 2), abs=1e-12)
    assert hi == pytest.approx(0.24 + math.sqrt((u1 - 0.27) ** 2 + (0.03 - l2) ** 2), abs=1e-12)
    assert round(lo, 2) == 0.15 and round(hi, 2) == 0.34
    assert excludes_zero(lo, hi)


def test_newcombe_1998_worked_example():
    # Newcombe (1998), Table II, example (a): 56/70 - 48/80, method 10: 0.0524 to 0.3339.
    lo, hi = newcombe_diff_ci(56, 70, 48, 80)
    assert lo == pytest.approx(0.0524, abs=1e-4)
    assert hi == pytest.approx(0.3339, abs=1e-4)


def test_newcombe_equal_arms_contain_zero():
    lo, hi = newcombe_diff_ci(0, 8, 0, 8)
    assert lo == pytest.approx(-hi) and not excludes_zero(lo, hi)
