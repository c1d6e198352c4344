"""The missed-mode check (treeinfer.inference.mode_check): its starts and its decision rule,
against a two-mode posterior whose modes and heights are known in closed form."""

import numpy as np
import pytest
from scipy.stats import chi2

from treeinfer.inference.mode_check import (
    BETTER_NATS,
    NEAR_NATS,
    flag_missed,
    trade_starts,
)


def test_trade_starts_move_one_stiffness_up_and_another_down():
    best = np.array([1.0, 2.0, 3.0, -1.0, 0.0, 1.0, -6.0])
    s = trade_starts(best, 3, steps=(0.5, -0.5))
    assert s.shape == (6, 7)  # 3 pairs x 2 steps
    d = s - best
    np.testing.assert_allclose(d[:, 3:], 0.0)  # dampings and noise untouched
    np.testing.assert_allclose(d[:, :3].sum(axis=1), 0.0)  # one up, one down
    assert np.all(np.sort(np.abs(d[:, :3]), axis=1)[:, 1:] == 0.5)
    assert trade_starts(best, 1).shape == (0, 7)  # one joint: nothing to trade


def test_flags_an_equal_mode_outside_the_particles_and_a_higher_one_anywhere():
    """Particles from N(0, I) in 7-D (mode A). End points: A's own mode (not missed), a mode B
    10 sd away at A's height (missed), B 10 nats lower (a mode the posterior may ignore: not
    flagged), a point inside A's cloud 2 nats ABOVE the best particle (the particles missed the
    top of their own mode: flagged)."""
    rng = np.random.default_rng(0)
    d = 7
    x = rng.standard_normal((256, d))
    b = np.zeros(d)
    b[0] = 10.0
    finals = np.stack([np.zeros(d), b, b, 0.1 * np.ones(d)])
    # nats above the best particle: A's mode a little above it (a draw of 256 in 7-D lies about
    # 0.5-1 nats below the peak), B at that height, B 10 nats lower, a point clearly above
    above = np.array([0.5, 0.5, -9.5, BETTER_NATS + 1.0])
    flagged, m2, limit = flag_missed(finals, above, x)
    assert limit == pytest.approx(chi2.ppf(0.999, d))
    assert m2[1] > limit > m2[0]
    assert list(flagged) == [False, True, False, True]


def test_an_end_point_just_below_the_particles_height_inside_them_is_not_flagged():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((200, 6))
    flagged, _, _ = flag_missed(np.zeros((2, 6)), np.array([-NEAR_NATS / 2, np.nan]), x)
    assert not flagged.any()  # inside the cloud, not higher; a failed (NaN) fit never flags
