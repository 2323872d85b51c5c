"""The position-only lever arm against a drifting odometry, pooled over drives (issue 24
item 4; docs/evaluating.md#errors-in-variables).

One prism tracked (exact, 10 Hz) on the body origin of a smooth 3-D loop; the odometry of a
sensor mounted 174 deg about an axis near the vertical with a lever arm of 0.5 m: white noise
1 cm and 0.5 deg, random walks 0.5 % and 0.05 deg per sqrt(m), in a random frame, its clock
``--clock`` s late. ``fit_mounting(..., estimate=ESTIMATE, align="se3")`` per seed; prints each
z (error / sigma) and the pooled mean z and mean z^2 (1 when the sigmas are honest).

    python benchmarks/mounting_prism.py --seeds 16 --estimate lever-xy
    python benchmarks/mounting_prism.py --seeds 12 --estimate lever-xy,clock --clock 0.05
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from rtsgt.errors import ExcitationError
from rtsgt.evaluation.mounting import fit_mounting
from rtsgt.geometry.so3 import exp_so3

AXIS = np.array([0.05, -0.03, 1.0]) / np.linalg.norm([0.05, -0.03, 1.0])
R_BS = exp_so3(np.radians(174.0) * AXIS)
LEVER = 0.5 * np.array([0.6, -0.7, 0.3]) / np.linalg.norm([0.6, -0.7, 0.3])


def loop(s: np.ndarray):
    """Positions (N, 3) and rotations (N, 3, 3) of the body at ``s`` seconds, and velocities."""
    p = np.c_[20 * np.sin(s / 30) + 0.3 * np.sin(s / 3),
              15 * np.sin(s / 20) * np.cos(s / 45), 0.5 * np.sin(s / 10)]
    v = np.c_[2 / 3 * np.cos(s / 30) + 0.1 * np.cos(s / 3),
              0.75 * np.cos(s / 20) * np.cos(s / 45) - 1 / 3 * np.sin(s / 20) * np.sin(s / 45),
              0.05 * np.cos(s / 10)]
    yaw = np.arctan2(v[:, 1], v[:, 0])
    R = Rotation.from_euler("ZYX", np.c_[yaw, 0.04 * np.cos(s / 5), 0.05 * np.sin(s / 4)])
    return p, R.as_matrix(), v


def drive(rng: np.random.Generator, n: int, clock: float):
    t = 1.0 + 0.1 * np.arange(n)
    p, _, v = loop(t)
    pb, R, _ = loop(t + clock)
    ps = pb + R @ LEVER
    dp = np.diff(ps, axis=0)
    ds = np.linalg.norm(dp, axis=1)
    yaw = np.r_[0.0, np.cumsum(rng.normal(size=ds.size) * np.radians(0.05) * np.sqrt(ds))]
    Rz = exp_so3(yaw[:, None] * np.array([0.0, 0.0, 1.0]))
    step = np.einsum("nij,nj->ni", Rz[:-1], dp) + rng.normal(size=dp.shape) * 0.005 * np.sqrt(
        ds)[:, None]
    pe = ps[0] + np.r_[np.zeros((1, 3)), np.cumsum(step, axis=0)] + 0.01 * rng.normal(
        size=(n, 3))
    Re = exp_so3(np.radians(0.5) * rng.normal(size=(n, 3))) @ Rz @ R @ R_BS
    Ra, ta = exp_so3(rng.normal(size=3)), 5.0 * rng.normal(size=3)
    return p, v, (pe - ta) @ Ra, Ra.T @ Re


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=16)
    ap.add_argument("--first-seed", type=int, default=100)
    ap.add_argument("--poses", type=int, default=800)
    ap.add_argument("--estimate", default="lever-xy")
    ap.add_argument("--clock", type=float, default=0.0)
    a = ap.parse_args()
    zs, refused, t0 = [], 0, time.perf_counter()
    for seed in range(a.first_seed, a.first_seed + a.seeds):
        p, v, pe, Re = drive(np.random.default_rng(seed), a.poses, a.clock)
        S = np.broadcast_to(np.eye(3) * 1e-6, (p.shape[0], 3, 3))
        try:
            fit = fit_mounting(p, None, S, pe, Re, estimate=a.estimate, align="se3",
                               rotation=R_BS, lever=np.r_[0.0, 0.0, LEVER[2]], gt_velocity=v)
        except ExcitationError as e:
            refused += 1
            print(seed, "refused:", e)
            continue
        err = (LEVER - fit.lever)[:2]
        if "clock" in a.estimate:
            err = np.r_[err, a.clock - fit.clock_offset]
        zs.append(err / np.sqrt(np.diagonal(fit.covariance)))
        print(seed, np.round(zs[-1], 2), {k: f"{v:.3g}" for k, v in fit.odometry.items()})
    zs = np.array(zs)
    print(f"{a.estimate}: mean z {np.round(zs.mean(0), 2)} (se {1 / np.sqrt(len(zs)):.2f}), "
          f"mean z^2 {np.round((zs ** 2).mean(0), 2)}; {refused} refused; "
          f"{time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
