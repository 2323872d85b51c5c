"""Weighted against unweighted registration: pose variance and honesty, on simulated deployments.

Run: ``python benchmarks/registration.py [--deployments 60] [--duration 150]
[--engines mc linear] [--samples 300] [--first-seed 12000]``

Every deployment ``first_seed + k`` is simulated (:mod:`rtsgt.simulation`, every noise source,
every systematic error drawn afresh), written as files, read back and run through the whole
pipeline once per engine with the weighted registration; the poses are then computed again
from the same interpolated prisms with the unweighted (the paper's) registration, exactly as
the pipeline's pose stage does (:func:`rtsgt.pose.estimate_poses` with the run's pose stream,
then the module 4 gates), so the two differ by the registration alone. Both are compared with
the exact truth.

Reported per engine and registration, pooled over all poses of all deployments: the position
(3 dof) and pose (6 dof) NEES / dof and the share inside the 95 % region; the median position
error; the median variance of the position and of the rotation (trace of each 3x3 block).
Per engine, at the pose times both keep: the median over poses of the reduction
``1 - tr_weighted / tr_unweighted`` of each block, and the 95th percentile of
``tr_unweighted / tr_weighted`` (the poses the weights help most).

The issue's acceptance: a median reduction of at least 20 % in position and 40 % in rotation,
with NEES / dof in [0.90, 1.10] and the 95 % regions holding 93-97 % of the truths.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.filtering.gates import apply_gates
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io.deployment import load_deployment
from rtsgt.options import stage_rng
from rtsgt.pipeline import run_pipeline
from rtsgt.pose import estimate_poses
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.types import PoseTrajectory

REGISTRATIONS = ("weighted", "unweighted")


def _poses(result, registration: str) -> PoseTrajectory:
    """The pipeline's pose stage on the run's prisms with another registration."""
    o = result.options
    c = result.computation
    ref = result.tracked_reference
    est = estimate_poses(c.prisms.xyz, c.prisms.pose_covariance, ref, engine=o.pose.engine,
                         registration=registration, samples=o.pose.samples,
                         rng=stage_rng(o.seed, "pose"))
    keep, _ = apply_gates(est, ref, distance_gate_m=o.pose.distance_gate_m,
                          uncertainty_gate_m=o.pose.uncertainty_gate_m)
    return PoseTrajectory(c.prisms.t[keep], est.t[keep], matrix_to_quat_xyzw(est.R[keep]),
                          est.cov[keep])


def run_engine(engine: str, seeds, duration: float, samples: int, tmp: Path) -> dict:
    """Pooled figures of both registrations for one engine."""
    parts = {reg: {"n3": [], "n6": [], "err": [], "tr_t": [], "tr_r": []} for reg in REGISTRATIONS}
    ratio_t, ratio_r = [], []
    for seed in seeds:
        sim = simulate_deployment(SimulationConfig(duration_s=duration),
                                  np.random.default_rng(seed))
        data, opts = load_deployment(write_deployment(sim, tmp / f"{engine}-{seed}"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = run_pipeline(data, opts.updated(seed=seed, engine=engine, samples=samples,
                                                     registration="weighted"))
            gts = {"weighted": result.groundtruth, "unweighted": _poses(result, "unweighted")}
        for reg, gt in gts.items():
            p, q = sim.truth_at(gt.t)
            c = compare_to_truth(gt, p, q)
            d = parts[reg]
            d["n3"].append(c.nees_position.values)
            d["n6"].append(c.nees_pose.values)
            d["err"].append(c.position_error_m)
            d["tr_t"].append(np.trace(gt.cov[:, :3, :3], axis1=1, axis2=2))
            d["tr_r"].append(np.trace(gt.cov[:, 3:, 3:], axis1=1, axis2=2))
        w, u = gts["weighted"], gts["unweighted"]
        common, iw, iu = np.intersect1d(w.t, u.t, return_indices=True)
        for blk, out in ((slice(0, 3), ratio_t), (slice(3, 6), ratio_r)):
            tw = np.trace(w.cov[iw][:, blk, blk], axis1=1, axis2=2)
            tu = np.trace(u.cov[iu][:, blk, blk], axis1=1, axis2=2)
            out.append(tw / tu)
    rows = {}
    for reg, d in parts.items():
        a3, a6 = np.concatenate(d["n3"]), np.concatenate(d["n6"])
        rows[reg] = {"poses": a3.size, "nees3": a3.mean() / 3,
                     "in3": np.mean(a3 <= chi2.ppf(0.95, 3)), "nees6": a6.mean() / 6,
                     "in6": np.mean(a6 <= chi2.ppf(0.95, 6)),
                     "err_mm": 1e3 * np.median(np.concatenate(d["err"])),
                     "tr_t_mm2": 1e6 * np.median(np.concatenate(d["tr_t"])),
                     "tr_r_mrad2": 1e6 * np.median(np.concatenate(d["tr_r"]))}
    rt, rr = np.concatenate(ratio_t), np.concatenate(ratio_r)
    gain = {"poses": rt.size, "median_cut_t": 1 - np.median(rt), "median_cut_r": 1 - np.median(rr),
            "p95_t": np.quantile(1 / rt, 0.95), "p95_r": np.quantile(1 / rr, 0.95)}
    return {"rows": rows, "gain": gain}


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=60)
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--engines", nargs="+", default=["mc", "linear"])
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--first-seed", type=int, default=12000)
    args = ap.parse_args(argv)
    seeds = range(args.first_seed, args.first_seed + args.deployments)
    print(f"{args.deployments} deployments x {args.duration:g} s, seeds {seeds.start}-"
          f"{seeds.stop - 1}, M = {args.samples} (mc)")
    print(f"{'engine':<7} {'registration':<11} {'poses':>7} {'NEES3/3':>8} {'in 95%':>7} "
          f"{'NEES6/6':>8} {'in 95%':>7} {'med err':>8} {'tr pos':>9} {'tr rot':>10} {'time':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        for engine in args.engines:
            t0 = time.perf_counter()
            r = run_engine(engine, seeds, args.duration, args.samples, Path(tmp))
            dt = time.perf_counter() - t0
            for reg, row in r["rows"].items():
                print(f"{engine:<7} {reg:<11} {row['poses']:>7d} {row['nees3']:>8.3f} "
                      f"{row['in3']:>7.3f} {row['nees6']:>8.3f} {row['in6']:>7.3f} "
                      f"{row['err_mm']:>5.2f} mm {row['tr_t_mm2']:>6.3f} mm2 "
                      f"{row['tr_r_mrad2']:>6.3f} mrad2 {dt:>5.0f}s")
            g = r["gain"]
            print(f"{engine:<7} weighted vs unweighted at {g['poses']} common poses: median "
                  f"variance cut {100 * g['median_cut_t']:.1f} % (position), "
                  f"{100 * g['median_cut_r']:.1f} % (rotation); 95th percentile of the ratio "
                  f"{g['p95_t']:.2f}x / {g['p95_r']:.2f}x")


if __name__ == "__main__":
    main()
