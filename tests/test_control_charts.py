"""Control charts of array-level readings (mlaqc.resultsdb.control) against series whose truth is known:
in-control normal values (false calls at the rate the rules are known for), a seeded creeping drift (called
within a few arrays of its onset), each rule on a series built to break it alone."""

import numpy as np
import pytest

from mlaqc.resultsdb.control import individuals_chart


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
