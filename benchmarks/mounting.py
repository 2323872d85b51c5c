"""The sensor mounting and the clock offset estimated by ``rtsgt evaluate``, against the truth.

Run: ``python benchmarks/mounting.py [--deployments 60] [--duration 120] [--engine linear]
[--align se3] [--estimate all] [--angle-deg 174] [--lever-m 0.5] [--clock-s 0.03]
[--est-sigma-m 0] [--first-seed 11000] [--odometry] [--per-run 1] [--verbose] [--example]``

For each deployment ``first_seed + k`` (:mod:`rtsgt.simulation`): simulate, write the files,
read them back, run the pipeline, write the run directory and load its continuous ground truth
(:func:`rtsgt.app.read_ground_truth`), as ``rtsgt evaluate`` does. The
estimate is the exact truth of a sensor mounted on the robot (``T_body_sensor``: a rotation of
``--angle-deg`` about an axis drawn within 10 deg of the vertical, a lever arm of
``--lever-m`` in a random direction; with ``lever-xy`` its z is given), seen in a random world frame (rotation and translation),
stamped on a clock ``--clock-s`` late (its pose at stamp ``t`` is the truth at
``t + clock``), at 10 Hz; with ``--est-sigma-m`` > 0, perturbed by that noise (and by
rotation noise of 0.2 rad per metre of it: 2 mrad for 1 cm) with its covariance given. It is evaluated with
``--estimate`` (from the identity mounting and a zero time offset) and, for comparison, with
the true mounting and clock given.

A deployment whose trajectory does not excite what is asked is refused (counted, with the
reason, and left out of the figures). Printed: the pooled NEES / dof of the estimated parameters against the truth (their estimate's
error against their covariance; the acceptance of issue 14: within [0.8, 1.2]), per group, the
share of deployments whose parameters fall inside their 95 % region, and the APE / RPE rmse
after estimating against those with the truth given, in units of the uncertainty the
estimation reports for them (``mounting.effect``).
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from rtsgt.app import read_ground_truth
from rtsgt.errors import ExcitationError
from rtsgt.evaluation import evaluate
from rtsgt.geometry.so3 import log_so3, matrix_to_quat_xyzw, quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturb
from rtsgt.io.deployment import load_deployment
from rtsgt.io.run_dir import write_run
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.types import PoseTrajectory


def mounting_truth(rng: np.random.Generator, angle_deg: float, lever_m: float):
    """``R_body_sensor`` (an axis within 10 deg of z) and ``t_body_sensor`` (random
    direction)."""
    tilt = np.radians(10.0) * np.sqrt(rng.uniform())
    az = rng.uniform(0, 2 * np.pi)
    axis = np.array([np.sin(tilt) * np.cos(az), np.sin(tilt) * np.sin(az), np.cos(tilt)])
    R_bs = Rotation.from_rotvec(np.radians(angle_deg) * axis).as_matrix()
    d = rng.normal(size=3)
    return R_bs, lever_m * d / np.linalg.norm(d)


def drifting_odometry(rng: np.random.Generator, R: np.ndarray, p: np.ndarray, *,
                      white_m: float, white_deg: float, drift: float,
                      drift_deg_m: float) -> tuple[np.ndarray, np.ndarray]:
    """A SLAM output of the sensor poses ``(R, p)`` (world frame): random walks with the
    distance driven of the position (``drift`` m per sqrt(m): a share of each metre) and of
    the yaw (``drift_deg_m`` deg per sqrt(m)), then white noise of ``white_m`` m and
    ``white_deg`` deg per axis on every pose. Returns ``(R, p)`` drifted and noisy."""
    dp = np.diff(p, axis=0)
    ds = np.linalg.norm(dp, axis=1)
    yaw = np.r_[0.0, np.cumsum(rng.normal(size=ds.size) * np.radians(drift_deg_m)
                               * np.sqrt(ds))]
    Rz = Rotation.from_rotvec(yaw[:, None] * np.array([0.0, 0.0, 1.0])).as_matrix()
    step = (np.einsum("nij,nj->ni", Rz[:-1], dp)
            + rng.normal(size=dp.shape) * drift * np.sqrt(ds)[:, None])
    pd = p[0] + np.r_[np.zeros((1, 3)), np.cumsum(step, axis=0)]
    xi = rng.normal(size=(p.shape[0], 6)) * np.r_[[white_m] * 3, [np.radians(white_deg)] * 3]
    return perturb(Rz @ R, pd, xi)


def simulated_run(seed: int, args, tmp: Path):
    """Simulate deployment ``seed``, run the pipeline, load its continuous ground truth."""
    sim = simulate_deployment(SimulationConfig(duration_s=args.duration),
                              np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep-{seed}"))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        rec = run_pipeline(data, opts.updated(seed=seed, engine=args.engine))
        run = write_run(rec, tmp / f"run-{seed}")
    return sim, read_ground_truth(run)


def one(seed: int, args, tmp: Path, cache: dict) -> dict:
    base = args.first_seed + (seed - args.first_seed) // args.per_run * args.per_run
    if cache.get("seed") != base:
        cache.update(seed=base, run=simulated_run(base, args, tmp))
    sim, gt = cache["run"]
    rng = np.random.default_rng(seed + 1)
    R_bs, lever = mounting_truth(rng, args.angle_deg, args.lever_m)
    Ra = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
    ta = rng.normal(size=3) * 10.0
    clock = rng.uniform(-0.5, 0.5) if args.odometry else args.clock_s
    odo = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        a, b = gt.span
        t = np.arange(a + 1.0, b - 1.0, 0.1)  # the estimate's stamps
        p, q = sim.truth_at(t + clock)  # T_world_body at the true times
        R = quat_xyzw_to_matrix(q)
        Rs, ps = R @ R_bs, p + R @ lever  # T_world_sensor
        cov = None
        if args.odometry:
            odo = {"white_m": rng.uniform(0.01, 0.05), "white_deg": 0.5,
                   "drift": rng.uniform(0.001, 0.01), "drift_deg_m": rng.uniform(0.01, 0.1)}
            Rs, ps = drifting_odometry(rng, Rs, ps, **odo)
        elif args.est_sigma_m > 0:
            s = args.est_sigma_m
            cov = np.broadcast_to(np.diag([s * s] * 3 + [(0.2 * s) ** 2] * 3),
                                  (t.size, 6, 6)).copy()
            xi = rng.normal(size=(t.size, 6)) * np.sqrt(np.diagonal(cov[0]))
            Rs, ps = perturb(Rs, ps, xi)
            cov = np.einsum("ij,njk,lk->nil", np.kron(np.eye(2), Ra.T), cov,
                            np.kron(np.eye(2), Ra.T))
        est = PoseTrajectory(t, (ps - ta) @ Ra, matrix_to_quat_xyzw(Ra.T @ Rs), cov)
        t0 = time.perf_counter()
        start = None  # the identity, except for a lever arm's z given with lever-xy
        if "lever-xy" in args.estimate:
            start = (0.0, 0.0, float(lever[2]), 0.0, 0.0, 0.0, 1.0)
        elif "lever" not in args.estimate and args.estimate != "all":  # the lever arm given
            start = (*lever, 0.0, 0.0, 0.0, 1.0)
        try:
            res = evaluate(gt, est, align=args.align, estimate=args.estimate, mounting=start)
        except ExcitationError as exc:
            return {"refused": str(exc)}
        dt = time.perf_counter() - t0
        given = evaluate(gt, est, align=args.align, time_offset=clock,
                         mounting=tuple(np.r_[lever, matrix_to_quat_xyzw(R_bs)]))
    m = res.mounting
    truth = {"rotation": log_so3(R_bs @ m.rotation.T), "lever": lever - m.lever,
             "clock": np.array([clock - m.clock_offset])}
    truth["lever-xy"] = truth["lever"][:2]
    err = np.concatenate([truth[g] for g in m.estimated])
    C = m.covariance
    nees = float(err @ np.linalg.solve(C, err))
    out = {"nees": nees, "dof": err.size, "seconds": dt, "groups": {}, "sigma": m.sigma,
           "n": m.n_used, "tau": m.time_correlation, "f": m.scale_factor, "start": m.start,
           "model": m.model, "odometry": odo, "levels": m.odometry,
           "clock_z": float(truth["clock"][0] / np.sqrt(C[-1, -1]))
           if "clock" in m.estimated else np.nan}
    k = 0
    for g in m.estimated:
        n = truth[g].size
        e, Cg = err[k:k + n], C[k:k + n, k:k + n]
        out["groups"][g] = float(e @ np.linalg.solve(Cg, e))
        k += n
    u = res.mounting_effect
    z = {}
    for key, a_, b_ in (
        ("ape_translation_m", res.ape.translation_m.rmse, given.ape.translation_m.rmse),
        ("ape_rotation_deg", res.ape.rotation_deg.rmse, given.ape.rotation_deg.rmse),
        ("rpe_translation_m", res.rpe.translation_m.rmse, given.rpe.translation_m.rmse),
        ("rpe_rotation_deg", res.rpe.rotation_deg.rmse, given.rpe.rotation_deg.rmse),
    ):
        z[key] = (a_ - b_, u[key])
    out["effect"] = z
    out["ape_mm"] = (1e3 * res.ape.translation_m.rmse, 1e3 * given.ape.translation_m.rmse)
    return out


def example(args) -> None:
    """The worked example of docs/evaluating.md#a-drifting-odometry: deployment ``--first-seed``
    (``--duration`` s), a SLAM output of a sensor mounted 174 deg about z with a lever arm
    (0.4, 0, 0.45) m, 0.3 s late, drifting 0.5 % and 0.05 deg per sqrt(m) with white noise of
    1 cm and 0.2 deg (a lidar odometry), evaluated without the mounting, with the rotation and
    the clock estimated (the lever arm given), and with the truth; then asked for the lever
    arm's horizontal components too."""
    rng = np.random.default_rng(args.first_seed + 1)
    R_bs = Rotation.from_rotvec(np.radians(174.0) * np.array([0.0, 0.0, 1.0])).as_matrix()
    lever, clock = np.array([0.4, 0.0, 0.45]), 0.3
    with tempfile.TemporaryDirectory() as tmp:
        sim, gt = simulated_run(args.first_seed, args, Path(tmp))
    a, b = gt.span
    t = np.arange(a + 1.0, b - 1.0, 0.1)
    p, q = sim.truth_at(t + clock)
    R = quat_xyzw_to_matrix(q)
    Rs, ps = drifting_odometry(rng, R @ R_bs, p + R @ lever, white_m=0.01, white_deg=0.2,
                               drift=0.005, drift_deg_m=0.05)
    est = PoseTrajectory(t, ps, matrix_to_quat_xyzw(Rs))
    runs = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        runs["mounting not given"] = evaluate(gt, est, align="se3")
        t0 = time.perf_counter()
        runs["estimated"] = evaluate(gt, est, align="se3", estimate="rotation,clock",
                                     mounting=(*lever, 0.0, 0.0, 0.0, 1.0))
        dt = time.perf_counter() - t0
        runs["truth given"] = evaluate(gt, est, align="se3", time_offset=clock,
                                       mounting=tuple(np.r_[lever, matrix_to_quat_xyzw(R_bs)]))
    print(f"{t.size} poses over {t[-1] - t[0]:.0f} s; the estimation {dt:.1f} s")
    for name, res in runs.items():
        n = res.nees.pose
        print(f"  {name}: APE {1e3 * res.ape.translation_m.rmse:.1f} mm / "
              f"{res.ape.rotation_deg.rmse:.3f} deg, RPE {1e3 * res.rpe.translation_m.rmse:.1f}"
              f" mm / {res.rpe.rotation_deg.rmse:.3f} deg, pose NEES "
              f"{n.mean if n is not None else float('nan'):.1f}")
    m = runs["estimated"].mounting
    rv = m.rotation_vector
    print(f"  estimated: rotation {np.degrees(np.linalg.norm(rv)):.3f} deg about "
          f"{np.round(rv / np.linalg.norm(rv), 4)}, sigma {np.degrees(m.group_sigma('rotation'))}"
          f" deg; lever {m.lever.round(4)} m, sigma {m.group_sigma('lever')} m; clock "
          f"{m.clock_offset:.4f} s, sigma {m.group_sigma('clock')[0]:.4f} s; model {m.model}; "
          f"odometry {m.odometry}")
    try:
        evaluate(gt, est, align="se3", estimate="rotation,lever-xy,clock",
                 mounting=(0.0, 0.0, 0.45, 0.0, 0.0, 0.0, 1.0))
        print("  rotation,lever-xy,clock: estimated")
    except ExcitationError as exc:
        print(f"  rotation,lever-xy,clock: error: {exc}")


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=60)
    ap.add_argument("--duration", type=float, default=120.0)
    ap.add_argument("--engine", default="linear")
    ap.add_argument("--align", default="se3")
    ap.add_argument("--estimate", default="all")
    ap.add_argument("--angle-deg", type=float, default=174.0)
    ap.add_argument("--lever-m", type=float, default=0.5)
    ap.add_argument("--clock-s", type=float, default=0.03)
    ap.add_argument("--est-sigma-m", type=float, default=0.0)
    ap.add_argument("--first-seed", type=int, default=11000)
    ap.add_argument("--odometry", action="store_true",
                    help="a drifting SLAM output (issue 24's acceptance): clock uniform in "
                         "[-0.5, 0.5] s, white noise 1-5 cm and 0.5 deg, drift 0.1-1 %% and "
                         "0.01-0.1 deg per sqrt(m)")
    ap.add_argument("--per-run", type=int, default=1,
                    help="estimates simulated on each simulated ground-truth run")
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--example", action="store_true",
                    help="the worked example of docs/evaluating.md (deployment --first-seed)")
    args = ap.parse_args(argv)
    if args.example:
        example(args)
        return
    t0 = time.perf_counter()
    rows, refused, cache = [], [], {}
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.deployments):
            r = one(args.first_seed + k, args, Path(tmp), cache)
            if "refused" in r:
                refused.append((args.first_seed + k, r["refused"]))
                if args.verbose:
                    print(f"{args.first_seed + k}: refused: {r['refused']}", flush=True)
                continue
            rows.append(r)
            if args.verbose:
                s = r["sigma"]
                print(f"{args.first_seed + k}: NEES/dof {r['nees'] / r['dof']:.2f} "
                      + " ".join(f"{g} {v:.2f}" for g, v in r["groups"].items())
                      + f" | sigma lever z {1e3 * s.get('lever_z', np.nan):.2f} mm, clock "
                      f"{1e3 * s.get('clock', np.nan):.3f} ms, tau {r['tau']:.2f}, f "
                      f"{r['f']:.2f}, start {r['start']}, {r['model']}, clock z "
                      f"{r['clock_z']:.2f}, {r['seconds']:.2f} s", flush=True)
    n = len(rows)
    dof = sum(r["dof"] for r in rows)
    pooled = sum(r["nees"] for r in rows) / dof
    inside = np.mean([r["nees"] <= chi2.ppf(0.95, r["dof"]) for r in rows])
    print(f"{n} deployments x {args.duration:g} s, engine {args.engine}, align {args.align}, "
          f"estimate {args.estimate}, mounting {args.angle_deg:g} deg / {args.lever_m:g} m, "
          f"clock {1e3 * args.clock_s:g} ms, estimate noise {args.est_sigma_m:g} m "
          f"({time.perf_counter() - t0:.0f} s; the fit and the evaluation "
          f"{np.median([r['seconds'] for r in rows]):.2f} s median per deployment)")
    print(f"pooled NEES / dof of the estimated parameters: {pooled:.3f} ({dof} dof; "
          f"+- {np.sqrt(2.0 / dof):.3f} expected spread); inside their 95 % region: "
          f"{100 * inside:.1f} % of the deployments")
    cz = np.array([r["clock_z"] for r in rows])
    if np.any(np.isfinite(cz)):
        print(f"clock within 2 sigma of the truth: {100 * np.mean(np.abs(cz) <= 2):.1f} %; "
              f"models: " + ", ".join(f"{k} {sum(r['model'] == k for r in rows)}"
                                      for k in ("absolute", "odometry")))
    print(f"refused: {len(refused)} of {n + len(refused)} deployments"
          + "".join(f"\n  {seed}: {why}" for seed, why in refused))
    for g in rows[0]["groups"]:
        k = {"rotation": 3, "lever": 3, "lever-xy": 2, "clock": 1}[g]
        print(f"  {g}: NEES / dof {sum(r['groups'][g] for r in rows) / (k * n):.3f}")
    for key in rows[0]["effect"]:
        d = np.array([r["effect"][key][0] for r in rows])
        u = np.array([r["effect"][key][1] for r in rows])
        print(f"  {key}: estimated - given rmse: median |diff| {np.median(np.abs(d)):.3g}, "
              f"median uncertainty {np.median(u):.3g}, |diff| <= 2 u in "
              f"{100 * np.mean(np.abs(d) <= 2 * u):.0f} %")
    print("  APE translation rmse (mm), median: estimated "
          f"{np.median([r['ape_mm'][0] for r in rows]):.3f}, given "
          f"{np.median([r['ape_mm'][1] for r in rows]):.3f}")


if __name__ == "__main__":
    main()
