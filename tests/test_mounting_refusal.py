"""The refusal rule of the mounting and clock estimate (issue 24): a parameter is refused when
its estimate would cost the evaluation more than giving it by hand (the clock: its sigma times
the ground truth's rms speed against the 2 cm of a lever arm by hand), or when the motion does
not excite it, with that reason (docs/evaluating.md#the-refusal-rule)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from rtsgt.errors import ExcitationError
from rtsgt.evaluation import evaluate
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from test_evaluation_mounting import LEVER, R_BS, T0, drifting


def test_a_noisy_drifting_drive_that_turns_gives_its_clock():
    """Three 30-s drives of a drifting odometry with 5 cm and 0.5 deg of white noise, clocks
    drawn in [-0.5, 0.5] s: the clock's sigma is 11-17 ms, which a fixed 10 ms limit refused
    (all 12 refusals of the 60-drive acceptance were such); its effect at the drive's rms speed
    (0.72 m/s) is below the 2 cm of a lever arm by hand, so each is estimated, and the clocks
    fall within 2 sigma of the truth (their pooled z^2 below chi2(3)'s 0.99 quantile)."""
    t = T0 + 1.0 + 0.1 * np.arange(300)
    z, sig = [], []
    for seed in (40, 41, 42):
        rng = np.random.default_rng(seed)
        clock = rng.uniform(-0.5, 0.5)
        est, gt = drifting(t, rng, clock=clock, white_m=0.05)
        m = evaluate(gt, est, align="se3", estimate="rotation,clock", max_dt=None,
                     mounting=(*LEVER, 0.0, 0.0, 0.0, 1.0)).mounting
        assert m.model == "odometry"
        assert m.limits["clock"] == pytest.approx(0.02 / 0.72, rel=0.05)
        sig.append(m.sigma["clock"])
        z.append((clock - m.clock_offset) / m.sigma["clock"])
    assert max(sig) > 0.01  # refused by the old rule
    assert np.all(np.abs(z) < 2.0)
    assert float(np.sum(np.square(z))) < chi2.ppf(0.99, 3)


def test_a_constant_velocity_drive_is_refused_for_the_excitation():
    """Driving straight at constant speed, a clock offset is a shift along the path that the
    alignment absorbs, whatever the odometry's error: refused, the motion named, with the
    limit the rms speed gives (0.02 m at 1 m/s: 0.02 s)."""
    t = T0 + 1.0 + 0.1 * np.arange(300)
    est, gt = drifting(t, np.random.default_rng(25), clock=0.2, straight=True)
    with pytest.raises(ExcitationError) as info:
        evaluate(gt, est, align="se3", estimate="clock", max_dt=None,
                 mounting=(*LEVER, *matrix_to_quat_xyzw(R_BS)))
    msg = str(info.value)
    assert msg.startswith("cannot estimate the clock offset: the trajectory does not excite it")
    assert "unbounded" in msg and "0.02 s" in msg and "1 m/s" in msg
    assert "accelerates or turns" in msg
