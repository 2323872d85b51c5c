"""What one solve of the joint engine's normal equations costs at an hour's size.

Run: ``python benchmarks/arrow_floor.py [--knots 23640] [--states 43] [--globals 82]
[--repeats 3] [--seed 0]``

Builds a random symmetric positive definite arrow system of the joint engine's shape
(:class:`rtsgt.joint.sparse.ArrowSystem`: ``K`` knots of ``d`` states, block tridiagonal, and
``G`` globals; the defaults are the field preset's hour: 6.6 knots per second, 43 states with
the chains, clocks, settling and rocking, 82 globals) and times
:func:`rtsgt.joint.sparse.solve_arrow` without and with the covariances (median of
``--repeats``, each on a fresh copy: the solve consumes it), with the process's peak resident
size. The floating-point operations per eliminated block are counted from the reduction's
products (docs/joint.md#an-hours-floor), so the run also says the throughput it reached.
Every Gauss-Newton iteration of the engine is one such solve, every variance-component update
one more with the covariances: the hour's time cannot fall below their count times these.
"""

from __future__ import annotations

import argparse
import resource
import time

import numpy as np

from rtsgt.joint.sparse import ArrowSystem, solve_arrow


def random_system(rng: np.random.Generator, K: int, d: int, G: int) -> ArrowSystem:
    """An SPD arrow system: each knot's block dominant over its two couplings and the
    globals' column (so the whole matrix is), the globals' block dominant over the knots'."""
    U = 0.3 * rng.standard_normal((K - 1, d, d)) / np.sqrt(d)
    B = 0.3 * rng.standard_normal((K, d, G)) / np.sqrt(d * G)
    M = rng.standard_normal((K, d, d)) / np.sqrt(d)
    D = M @ np.swapaxes(M, 1, 2) + 3.0 * np.eye(d)
    C = (1.0 + K * 0.1) * np.eye(G)
    return ArrowSystem(D, U, B, C, rng.standard_normal((K, d)), rng.standard_normal(G))


def flops(K: int, d: int, G: int, want_cov: bool) -> float:
    """Floating-point operations of one solve: per eliminated block (about ``K`` in all
    levels) the pivot's Cholesky inverse (``d^3``), its couplings (``4 d^3``) and their update
    of the neighbours (``6 d^3``), the forward pass of ``G + 1`` columns (``6 d^2 m``) and
    the Schur complement's sum (``2 d m^2``); with the covariances the back pass (``4 d^2
    m``), the inverse's blocks (``12 d^3``) and the globals' share (``4 d^2 G``)."""
    m = G + 1
    per = 11 * d**3 + 6 * d**2 * m + 2 * d * m**2
    if want_cov:
        per += 4 * d**2 * m + 12 * d**3 + 4 * d**2 * G
    return float(K) * per


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--knots", type=int, default=23640)
    ap.add_argument("--states", type=int, default=43)
    ap.add_argument("--globals", type=int, default=82, dest="n_globals")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    K, d, G = args.knots, args.states, args.n_globals
    base = random_system(np.random.default_rng(args.seed), K, d, G)
    print(f"{K} knots x {d} states, {G} globals")
    for want_cov in (False, True):
        times = []
        for _ in range(args.repeats):
            system = ArrowSystem(base.D.copy(), base.U.copy(), base.B, base.C, base.a, base.c)
            t0 = time.perf_counter()
            sol = solve_arrow(system, want_cov=want_cov, overwrite=True)
            times.append(time.perf_counter() - t0)
            del system, sol
        med = float(np.median(times))
        label = "with covariances" if want_cov else "without covariances"
        print(f"{label}: median {med:.2f} s of {args.repeats} ({min(times):.2f}-{max(times):.2f}),"
              f" {flops(K, d, G, want_cov) / med / 1e9:.1f} GFlop/s")
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    print(f"peak resident size {peak:.2f} GiB (the system itself "
          f"{(base.D.nbytes + base.U.nbytes + base.B.nbytes) / 2**30:.2f} GiB)")


if __name__ == "__main__":
    main()
