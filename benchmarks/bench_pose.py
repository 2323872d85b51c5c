"""Pose benchmarks: rigid-registration throughput and pose-engine throughput.

Run: ``python benchmarks/bench_pose.py [--solves 1e7] [--poses 500] [--samples 1000]``.
Prints medians over repeats. Target (issue 4): 1e7 three-point registrations in under 10 s
on a 2-core machine.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from scipy.spatial.transform import Rotation

from rtsgt.geometry import kabsch
from rtsgt.pose import estimate_poses, register


def warthog_problems(rng: np.random.Generator, B: int, noise: float = 0.003):
    """B registrations of the paper's prism triangle (0.74 / 0.90 / 1.03 m), noisy, far away."""
    d12, d13, d23 = 0.73555, 0.90303, 1.03046
    x = (d12**2 + d13**2 - d23**2) / (2 * d12)
    r = np.array([[0.0, 0.0, 0.5], [d12, 0.0, 0.5], [x, np.sqrt(d13**2 - x**2), 0.5]])
    R = Rotation.random(B, random_state=rng).as_matrix()
    t = rng.uniform(-150, 150, size=(B, 3))
    p = r + rng.normal(size=(B, 3, 3)) * 0.0007
    q = np.einsum("bij,nj->bni", R, r) + t[:, None] + rng.normal(size=(B, 3, 3)) * noise
    return r, p, q


def timed(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--solves", type=float, default=1e7, help="registrations in the big run")
    ap.add_argument("--poses", type=int, default=500, help="poses of the engine benchmark")
    ap.add_argument("--samples", type=int, default=1000, help="Monte Carlo samples per pose")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    rng = np.random.default_rng(0)

    block = 1_000_000
    _, p, q = warthog_problems(rng, block)
    t_block = timed(lambda: register(p, q), args.repeats)
    print(f"register, 3 points: {t_block:.3f} s per 1e6 solves (median of {args.repeats}) "
          f"= {block / t_block:.3g} solves/s")
    n_blocks = max(1, int(round(args.solves / block)))
    t0 = time.perf_counter()
    for _ in range(n_blocks):
        register(p, q)
    total = time.perf_counter() - t0
    print(f"register, 3 points: {n_blocks * block:.0e} solves in {total:.2f} s "
          f"(target: 1e7 in < 10 s)")
    small = 100_000
    t_svd = timed(lambda: kabsch(p[:small], q[:small], check=False), args.repeats)
    print(f"geometry.kabsch (batched SVD), 3 points: {small / t_svd:.3g} solves/s "
          f"-> closed form is {t_svd / small * block / t_block:.1f}x faster")

    T, M = args.poses, args.samples
    r, _, q_mean = warthog_problems(rng, T, noise=0.0)
    A = rng.normal(size=(T, 3, 3, 3)) * 0.002
    cov_q = A @ np.swapaxes(A, -1, -2) + np.eye(3) * 1e-6
    cov_r = np.eye(9) * (0.7e-3) ** 2
    t_mc = timed(lambda: estimate_poses(q_mean, cov_q, r, cov_r, engine="mc", samples=M,
                                        rng=np.random.default_rng(1)), args.repeats)
    print(f"estimate_poses mc: {T} poses x {M} samples in {t_mc:.2f} s = "
          f"{T / t_mc:.3g} poses/s, {T * M / t_mc:.3g} registrations/s (sampling included)")
    for engine in ("ut", "linear"):
        te = timed(lambda e=engine: estimate_poses(q_mean, cov_q, r, cov_r, engine=e),
                   args.repeats)
        print(f"estimate_poses {engine}: {T} poses in {te * 1e3:.1f} ms = {T / te:.3g} poses/s")


if __name__ == "__main__":
    main()
