"""Control charts of array-level readings (mlaqc.resultsdb.control) against series whose truth is known:
in-control normal values (false calls at the rate the rules or the CUSUM's design give), a seeded creeping
drift (called within a few arrays of its onset), each rule on a series built to break it alone, and the
self-starting scores against Student's t."""

import numpy as np
import pytest
from scipy import stats

from mlaqc.resultsdb.control import cusum_chart, individuals_chart


def test_limits_are_the_baselines_mean_and_moving_range():
    x = np.array([10.0, 12.0, 11.0, 13.0, 12.0] + [12.0] * 5)
    chart = individuals_chart(x, baseline=5)
    assert chart.centre == pytest.approx(11.6)
    assert chart.sigma == pytest.approx(np.mean([2, 1, 2, 1]) / 1.128)


@pytest.mark.parametrize("rule, tail", [
    (1, [0.0, 3.5]),                              # beyond 3 sigma
    (2, [0.0, 2.5, 0.0, 2.5]),                    # 2 of 3 beyond 2 sigma
    (3, [0.0, 1.5, 1.5, 0.5, 1.5, 1.5]),          # 4 of 5 beyond 1 sigma
    (4, [0.0, 0.3, 0.2, 0.4, 0.1, 0.3, 0.2, 0.4, 0.3]),  # 8 on one side
    (5, [-0.9, -0.6, -0.3, 0.0, 0.3, 0.6]),        # 6 rising
])
def test_each_rule_on_a_series_that_breaks_it(rule, tail):
    base = np.array([1.0, -1.0] * 10)  # centre 0, moving range 2: sigma 2 / 1.128
    sigma = 2 / 1.128
    chart = individuals_chart(np.concatenate([base, np.array(tail) * sigma]), baseline=20)
    last = 20 + len(tail) - 1
    assert rule in chart.signals.get(last, []), chart.signals
    assert chart.first_signal == last or rule in (2, 3, 4, 5)


def test_in_control_false_calls_and_a_creeping_drift():
    rng = np.random.default_rng(0)
    first = []
    for _ in range(300):
        chart = individuals_chart(rng.normal(0, 1, 320), baseline=20)
        first.append(300 if chart.first_signal is None else chart.first_signal - 20)
    # what the module docstring states: the first false call after a median of ~34 in-control arrays
    assert 25 <= np.median(first) <= 45
    quiet = []
    for _ in range(300):
        chart = individuals_chart(rng.normal(0, 1, 320), baseline=20, rules=(1, 5))
        quiet.append(300 if chart.first_signal is None else chart.first_signal - 20)
    assert 70 <= np.median(quiet) <= 120
    delay = []
    for _ in range(300):
        x = rng.normal(0, 1, 140)
        x[60:] += 0.25 * np.arange(1, 81)  # a quarter sigma more with every array from array 60 on
        chart = individuals_chart(x, baseline=20)
        after = [i for i in chart.signals if i >= 60]
        delay.append(after[0] - 60 if after else 99)
    assert np.median(delay) <= 7 and np.percentile(delay, 95) <= 11


def test_a_baseline_without_spread_calls_any_change_and_nothing_else():
    x = np.array([0.01] * 25 + [0.01000001] + [0.01] * 3)
    chart = individuals_chart(x, baseline=20)
    assert chart.sigma == 0 and chart.signals == {25: [1]}


def test_self_starting_scores_are_standard_normal_from_the_third_array():
    """An array judged against only two before it: (x - mean) / sd * sqrt(2/3) is Student's t with one
    degree of freedom (Cauchy), and its score is that t's quantile mapped onto the normal: N(0, 1) exactly,
    however short the history. Checked by a KS test of 4,000 series, and one score by hand."""
    rng = np.random.default_rng(7)
    scores = []
    for _ in range(4000):
        x = rng.normal(5.0, 3.0, 3)
        chart = cusum_chart(x, baseline=2, h=1e9)
        u = chart.cusum[0, 2] - chart.cusum[1, 2]  # one step: upper = max(0, u - k), lower = max(0, -u - k)
        if abs(u) > 0:
            scores.append(np.sign(u) * (abs(u) + 0.5))
    scores = np.array(scores)  # the |u| <= k ones sum to 0 both ways: only |u| > 0.5 are read back
    assert stats.kstest(np.abs(scores), lambda v: (stats.norm.cdf(v) - stats.norm.cdf(0.5)) / stats.norm.sf(0.5)).pvalue > 1e-3
    x = np.array([1.0, 3.0, 10.0])  # mean 2, sd sqrt(2), t = 8 / sqrt(2) * sqrt(2/3) on 1 dof
    t = 8 / np.sqrt(2) * np.sqrt(2 / 3)
    chart = cusum_chart(x, baseline=2, h=1e9)
    assert chart.cusum[0, 2] == pytest.approx(stats.norm.isf(stats.t.sf(t, 1)) - 0.5, rel=1e-9)
    assert chart.centre_at[2] == pytest.approx(2.0) and chart.sigma_at[2] == pytest.approx(np.sqrt(2))


@pytest.mark.parametrize("baseline", [3, 20])
def test_cusum_false_calls_do_not_depend_on_the_baseline(baseline):
    """In control, the design's rate whatever the baseline: a call within 49 judged arrays in about 4 % of
    series (k 0.5, h 6: run length ~1,200 on average); an I-MR chart's limits from 3 arrays would call one in
    most series."""
    rng = np.random.default_rng(baseline)
    calls = [cusum_chart(rng.normal(0, 1, baseline + 49), baseline=baseline).first_signal is not None
             for _ in range(1200)]
    assert np.mean(calls) <= 0.07
    imr = [individuals_chart(rng.normal(0, 1, baseline + 49), baseline=baseline, rules=(1,)).first_signal is not None
           for _ in range(300)]
    assert baseline == 20 or np.mean(imr) > 0.3


def test_cusum_calls_drifts_and_holds_them():
    """A drift of a quarter sigma per array is called after a median of 9 arrays; one of a sigma per array
    within its first 5 (almost always); a sustained step of 3 sigma at once and on every array after it
    (the estimates stop learning at the first call: the new level is not taken for the process)."""
    rng = np.random.default_rng(3)
    for slope, median_max, share_in_5 in ((0.25, 10, None), (1.0, 4, 0.97)):
        delay = []
        for _ in range(300):
            x = rng.normal(0, 1, 140)
            x[60:] += slope * np.arange(1, 81)
            after = [i for i in cusum_chart(x, baseline=20).signals if i >= 60]
            delay.append(after[0] - 59 if after else 99)
        assert np.median(delay) <= median_max
        assert share_in_5 is None or np.mean(np.array(delay) <= 5) >= share_in_5
    x = rng.normal(0, 1, 80)
    x[50:] += 3.0
    chart = cusum_chart(x, baseline=20)
    assert set(range(52, 80)) <= set(chart.signals) and chart.centre == pytest.approx(x[: chart.first_signal].mean())


def test_cusum_of_a_reading_without_spread_calls_any_change():
    x = np.array([0.01] * 25 + [0.01000001] + [0.01] * 3)
    chart = cusum_chart(x, baseline=20)
    assert chart.sigma == 0 and chart.signals == {25: ["jump"]}


def _rules_one_point(z, i):
    """The Western Electric and trend rules point i breaks, written out one point at a time (the reference
    the chart's all-points-at-once reading is checked against)."""
    out = []
    if abs(z[i]) > 3:
        out.append(1)
    for rule, (n, k, level) in ((2, (3, 2, 2.0)), (3, (5, 4, 1.0))):
        w = z[max(0, i - n + 1): i + 1]
        if w.size == n and any(np.count_nonzero(s * w > level) >= k and s * z[i] > level for s in (1, -1)):
            out.append(rule)
    w = z[max(0, i - 7): i + 1]
    if w.size == 8 and (np.all(w > 0) or np.all(w < 0)):
        out.append(4)
    w = z[max(0, i - 5): i + 1]
    if w.size == 6 and (np.all(np.diff(w) > 0) or np.all(np.diff(w) < 0)):
        out.append(5)
    return out


@pytest.mark.parametrize("rules", [(1, 2, 3, 4, 5), (1, 5), (3,)])
def test_imr_rules_read_at_once_are_the_rules_point_by_point(rules):
    rng = np.random.default_rng(len(rules))
    for trial in range(40):
        x = rng.normal(0, 1, 120) + np.where(np.arange(120) > 70, 0.1 * trial * np.arange(120) / 120, 0.0)
        chart = individuals_chart(x, baseline=20, rules=rules)
        z = (x - chart.centre) / chart.sigma
        expected = {i: [r for r in _rules_one_point(z, i) if r in rules] for i in range(20, 120)}
        assert chart.signals == {i: r for i, r in expected.items() if r}


def test_one_wild_array_is_a_jump_not_a_lasting_rise():
    """A reading misread by 10,000 sigma (its t tail underflows) is called at once as a jump; its score
    enters the sums clipped to the jump limit, so the in-control arrays after it are not called a sustained
    rise (unclipped, every later array was), and every sum stays finite."""
    rng = np.random.default_rng(9)
    x = rng.normal(0, 1, 300)
    x[100] = 1e4
    chart = cusum_chart(x, baseline=20)
    assert "jump" in chart.signals[100] and np.isfinite(chart.cusum).all()
    assert not [i for i, r in chart.signals.items() if "rise" in r and 100 < i < 130]


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_a_value_that_is_not_a_number_is_refused_by_name(bad):
    x = np.zeros(40) + np.random.default_rng(1).normal(0, 1, 40)
    x[30] = bad
    for chart in (cusum_chart, individuals_chart):
        with pytest.raises(ValueError, match="value #31"):
            chart(x)


def test_the_jump_limits_are_where_jumps_are_called():
    """`Chart.jump_limits` (what the lot report draws): a value just inside an array's limit is not a jump,
    just outside it is; at 20 arrays judged against, the limit is 5.2 sigma of them, not 4."""
    rng = np.random.default_rng(2)
    x = rng.normal(0, 1, 40)
    low, high = cusum_chart(x, baseline=20).jump_limits()
    for i, side in ((25, high), (30, low)):
        for factor, called in ((0.999, False), (1.001, True)):
            y = x.copy()
            y[i] = side[i] + (factor - 1) * (side[i] - x[:i].mean())
            assert ("jump" in cusum_chart(y, baseline=20).signals.get(i, [])) == called, (i, factor)
    chart = cusum_chart(x, baseline=20)
    assert (high[20] - chart.centre_at[20]) / chart.sigma_at[20] == pytest.approx(5.23, abs=0.02)
