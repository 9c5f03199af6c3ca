"""Learning-curve bands stay readable: drawn only where at least `MIN_BAND_RUNS` runs contribute
(two runs' Student-t band is +-12.7 standard errors wide and flattened every other line)."""

from __future__ import annotations

import numpy as np

from sitl_bridge.rl.analysis.plots import MIN_BAND_RUNS, mean_and_band


def test_the_band_is_left_out_where_fewer_than_three_runs_remain() -> None:
    assert MIN_BAND_RUNS == 3
    long_runs = [np.array([0.0, 10.0, 20.0, 30.0]), np.array([2.0, 12.0, 22.0, 3000.0]),
                 np.array([1.0, 11.0, 21.0])]  # the third ended after 3 episodes
    mean, low, high = mean_and_band(long_runs)
    assert np.allclose(mean, [1.0, 11.0, 21.0, 1515.0])
    assert np.all(np.isfinite(low[:3])) and np.all(low[:3] < mean[:3]) and np.all(high[:3] > mean[:3])
    assert np.isnan(low[3]) and np.isnan(high[3])  # two runs left: the mean only
    mean, low, high = mean_and_band(long_runs[:2])
    assert np.all(np.isnan(low)) and np.all(np.isnan(high)) and np.allclose(mean[:3], [1.0, 11.0, 21.0])
    mean, low, high = mean_and_band(long_runs[:1])
    assert np.all(np.isnan(low)) and np.allclose(mean, long_runs[0])
