"""A position-only ground truth (one tracked prism) evaluated with a lever arm: how honest it is.

Run: ``python benchmarks/positions.py [--deployments 40] [--duration 150] [--first-seed 1000]
[--stations 1]``

For each deployment ``first_seed + k`` (:mod:`rtsgt.simulation`): simulate, write the files,
read them back, keep the first ``--stations`` stations (station 1 tracking prism 1 alone by
default: a run of positions, no pose), run the pipeline and take prism 1's continuous ground
truth (:class:`rtsgt.evaluation.ContinuousPositionGroundTruth`). The estimate is the truth in
a sensor frame turned half a turn about z (and tilted) from the body frame, 0.6 m from it, at
10 Hz off the ground truth's grid; it is evaluated with the prism's lever arm in that frame
(:func:`rtsgt.evaluation.evaluate_positions`) without alignment and after the point-set
alignments, weighted (generalised least squares) and not, and 1 cm off (in the world frame,
no alignment; in the lever arm, weighted SE(3)). Printed per case: the pooled position NEES
/ dof, the share inside the 95 % region, the deployments judged consistent and the range of
the per-deployment NEES / dof; and the relative-position NEES of the truth. The table of
docs/evaluation.md#position-only-ground-truth is this script's output for the defaults.
"""

from __future__ import annotations

import argparse
import dataclasses
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rtsgt.evaluation import ContinuousPositionGroundTruth, evaluate_positions
from rtsgt.geometry.so3 import matrix_to_quat_xyzw
from rtsgt.io.deployment import load_deployment
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory

R_BS = Rotation.from_euler("zyx", [np.pi, 0.02, -0.01]).as_matrix()
T_BS = np.array([0.3, 0.1, 0.5])
#: (name, estimate kind, alignment, weighted)
CASES = (
    ("truth, no alignment", "truth", "none", False),
    ("truth, SE(3) weighted", "truth", "se3", True),
    ("truth, Sim(3) weighted", "truth", "sim3", True),
    ("truth, 4-DOF weighted", "truth", "4dof", True),
    ("truth, SE(3) unweighted", "truth", "se3", False),
    ("1 cm off (world), no alignment", "bias", "none", False),
    ("1 cm off (lever arm), SE(3) weighted", "lever", "se3", True),
)


def one(seed: int, args, tmp: Path) -> dict:
    sim = simulate_deployment(SimulationConfig(duration_s=args.duration),
                              np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep-{seed}"))
    data = dataclasses.replace(data, observations=data.observations[:args.stations],
                               reference=None)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=seed))
    gt = ContinuousPositionGroundTruth.from_record(rec, "1")
    t = np.arange(rec.prisms_t[0] - 5.0, rec.prisms_t[-1] + 5.0, 0.1) + 0.0123
    R_wb, p_wb = sim.truth.model.body_at(t)
    lever = R_BS.T @ (sim.truth.reference_body[0] - T_BS)
    est = PoseTrajectory(t, p_wb + R_wb @ T_BS, matrix_to_quat_xyzw(R_wb @ R_BS))
    estimates = {"truth": (est, lever),
                 "bias": (dataclasses.replace(est, position=est.position + [0.006, -0.008, 0]),
                          lever),
                 "lever": (est, lever + np.array([0.0, 0.01, 0.0]))}
    out = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, kind, align, weighted in CASES:
            e, lv = estimates[kind]
            r = evaluate_positions(gt, e, lv, align=align, weighted=weighted, max_dt=3.0)
            out[name] = r.nees.position
            if name == "truth, no alignment":
                out["relative"] = r.nees.relative_position
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=40)
    ap.add_argument("--duration", type=float, default=150.0)
    ap.add_argument("--first-seed", type=int, default=1000)
    ap.add_argument("--stations", type=int, default=1, choices=(1, 2))
    args = ap.parse_args()
    start = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        runs = [one(args.first_seed + k, args, Path(d)) for k in range(args.deployments)]
    q95 = chi2.ppf(0.95, 3)
    print(f"{args.deployments} deployments of {args.duration:g} s, seeds {args.first_seed}-"
          f"{args.first_seed + args.deployments - 1}, {args.stations} station(s)")
    print(f"{'case':40s} {'NEES/dof':>9s} {'in 95 %':>8s} {'consistent':>11s} {'per run':>12s}")
    for name in [c[0] for c in CASES] + ["relative"]:
        v = np.concatenate([r[name].values for r in runs])
        per = [r[name].mean / 3 for r in runs]
        ok = sum(bool(r[name].consistent) for r in runs)
        print(f"{name:40s} {v.mean() / 3:9.3f} {100 * np.mean(v <= q95):7.1f}% "
              f"{ok:>5d} / {len(runs):<4d} {min(per):5.2f}-{max(per):5.2f}")
    print(f"{time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
