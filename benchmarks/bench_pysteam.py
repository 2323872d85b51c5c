"""Benchmark: rtsgt's exact GP versus pysteam used the way of Vaidis et al. (2023).

The paper interpolated each prism track with pysteam (PyPI ``asrl-pysteam``): one SE(3) knot
per measurement (identity rotations, constant-velocity WNOA prior on SE(3) with
``Qc = ones(6)``), one point-to-point error term per measurement weighted by the inverse of its
3x3 covariance, Gauss-Newton, then ``Covariance(problem)`` (a dense inverse of the whole
Hessian) and ``get_covariance`` at every query time (RTS_project,
``scripts/groundtruth_utils.py``, ``STEAM_interpolation_with_covariance``).

This script runs both on the same simulated track (N = 100 and 400 measurements, one query
per measurement time plus one between each pair), reports the median wall time of each and
their ratio, and checks that both posterior means agree to the sub-millimetre when rtsgt is
given the translational part of pysteam's Qc (``Qc = I`` m^2/s^3).

pysteam is an optional benchmark dependency: when it cannot be imported the script says so
and exits with status 0. Run: ``python benchmarks/bench_pysteam.py [--repeat 3]``.
"""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from rtsgt.interpolation import fit_track


def simulate(n: int, rng: np.random.Generator):
    """A prism driving a smooth curve, measured every ~0.4 s with mm-level covariances."""
    t = np.cumsum(rng.uniform(0.35, 0.45, n))
    t -= t[0]
    truth = np.stack([3.0 * np.sin(0.05 * t) + 0.5 * t, 2.0 * np.cos(0.07 * t), 0.1 * t], 1)
    a = rng.normal(size=(n, 3, 3)) * 1.5e-3
    cov = a @ np.swapaxes(a, 1, 2) + 1e-6 * np.eye(3)
    xyz = truth + np.einsum("nij,nj->ni", np.linalg.cholesky(cov), rng.normal(size=(n, 3)))
    return t, xyz, cov


def run_rtsgt(t, xyz, cov, tq):
    gp = fit_track((t, xyz, cov), qc=1.0, max_gap_s=np.inf)
    res = gp.query(tq)
    return res.position, res.position_cov


def run_pysteam(t, xyz, cov, tq):
    """The paper's way (see the module docstring)."""
    from pylgmath import Transformation
    from pysteam.evaluable.p2p import P2PErrorEvaluator
    from pysteam.evaluable.se3 import SE3StateVar
    from pysteam.evaluable.vspace import VSpaceStateVar
    from pysteam.problem import (
        L2LossFunc,
        OptimizationProblem,
        StaticNoiseModel,
        WeightedLeastSquareCostTerm,
    )
    from pysteam.solver import Covariance, GaussNewtonSolver
    from pysteam.trajectory import Time
    from pysteam.trajectory.const_vel import Interface as TrajectoryInterface

    n = t.shape[0]
    meas = np.concatenate([xyz, np.ones((n, 1))], axis=1)[:, :, None]
    states = [
        (t[i], Transformation(C_ba=np.eye(3), r_ba_in_a=meas[i, :3]), np.zeros((6, 1)))
        for i in range(n)
    ]
    state_vars = [(ti, SE3StateVar(T), VSpaceStateVar(w)) for ti, T, w in states]
    traj = TrajectoryInterface(qcd=np.ones(6))
    for ti, T, w in state_vars:
        traj.add_knot(time=Time(ti), T_k0=T, w_0k_ink=w)
    loss = L2LossFunc()
    costs = []
    for i in range(n):
        noise = StaticNoiseModel(np.linalg.inv(cov[i]), "information")
        err = P2PErrorEvaluator(
            T_rq=state_vars[i][1], reference=np.array([[0.0, 0, 0, 1]]).T, query=meas[i]
        )
        costs.append(WeightedLeastSquareCostTerm(err, noise, loss))
    problem = OptimizationProblem()
    problem.add_state_var(*[v for sv in state_vars for v in sv[1:]])
    problem.add_cost_term(*traj.get_prior_cost_terms())
    problem.add_cost_term(*costs)
    GaussNewtonSolver(problem, verbose=False).optimize()
    covariance = Covariance(problem)
    position = np.empty((tq.shape[0], 3))
    pcov = np.empty((tq.shape[0], 3, 3))
    for j, tj in enumerate(tq):
        T_k0 = traj.get_pose_interpolator(Time(tj)).evaluate().matrix()
        position[j] = np.linalg.inv(T_k0)[:3, 3]
        pcov[j] = traj.get_covariance(covariance, Time(tj))[:3, :3]
    return position, pcov


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--sizes", type=int, nargs="+", default=[100, 400])
    args = parser.parse_args(argv)
    try:
        import pysteam  # noqa: F401
        from pylgmath import Transformation  # noqa: F401
    except Exception as exc:  # pragma: no cover - optional dependency
        print(f"pysteam is not available ({exc}); `pip install asrl-pysteam` to run this "
              "benchmark. Nothing to do.")
        return 0
    rng = np.random.default_rng(20221110)
    print(f"{'N':>5} {'rtsgt (s)':>10} {'pysteam (s)':>12} {'ratio':>8} "
          f"{'max |dp| (mm)':>14} {'median sigma rtsgt/pysteam (mm)':>32}")
    worst = 0.0
    for n in args.sizes:
        t, xyz, cov = simulate(n, rng)
        tq = np.sort(np.concatenate([t, 0.5 * (t[1:] + t[:-1])]))
        times = {"rtsgt": [], "pysteam": []}
        out = {}
        for _ in range(args.repeat):
            t0 = time.perf_counter()
            out["rtsgt"] = run_rtsgt(t, xyz, cov, tq)
            times["rtsgt"].append(time.perf_counter() - t0)
        for _ in range(max(1, args.repeat if n <= 100 else 1)):
            t0 = time.perf_counter()
            out["pysteam"] = run_pysteam(t, xyz, cov, tq)
            times["pysteam"].append(time.perf_counter() - t0)
        tr, tp = np.median(times["rtsgt"]), np.median(times["pysteam"])
        dp = np.abs(out["rtsgt"][0] - out["pysteam"][0]).max() * 1e3
        worst = max(worst, dp)
        sig = [np.median(np.sqrt(np.trace(out[k][1], axis1=1, axis2=2) / 3)) * 1e3
               for k in ("rtsgt", "pysteam")]
        print(f"{n:>5} {tr:>10.4f} {tp:>12.3f} {tp / tr:>8.0f} {dp:>14.4f} "
              f"{sig[0]:>15.3f} / {sig[1]:<15.3f}")
    ok = worst < 1.0
    print(f"means agree to the sub-millimetre: {'yes' if ok else 'NO'} (max {worst:.4f} mm)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
