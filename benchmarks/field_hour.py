"""Today's per-prism engine on simulated field hours: the baseline of issue 23.

Run: ``python benchmarks/field_hour.py [--seeds 0-4] [--duration 3600] [--engine ENGINE]``

For each seed, what a user does: ``rtsgt simulate --preset field-hour --seed S`` (the field
noise, clocks and moved prism of :mod:`rtsgt.simulation.field`, one far station, the prisms'
deviation, settling tripods; docs/simulation.md#the-field-hour-preset), the files read back
and run with the deployment's defaults (seed S; ``--engine`` overrides the pose engine).
Against the simulation's truth:

- pose (6 dof) NEES / dof and the share of poses whose 95 % region holds the truth
  (:func:`rtsgt.simulation.compare.compare_to_truth`), and the split test's verdict;
- relative-pose NEES / dof over 1, 10 and 60 s: consecutive pairs that far apart
  (:func:`rtsgt.evaluation.metrics.rpe_pairs`, pairs across a gap dropped), their covariance
  with the poses' cross-covariance from the run's continuous ground truth
  (:meth:`rtsgt.evaluation.ContinuousGroundTruth.pair_covariances`);
- the inter-prism distance check's mean z^2 and its accepted interval, the run's verdict,
  the median pose position sigma (``sqrt`` of the trace: the size of the position error it
  predicts), the median position error against the truth (the precision the engine has,
  whatever its covariance says) and the run's wall time (``run_pipeline`` alone);
- with the joint engine: the clocks', the deviation's, the Gauss-Markov chains' and the
  white noise's shares within 2 sigma of the truth (and each seed's z of the last two), the
  raw block cross-validation, and the prism the truth moved with those found and carried
  (:func:`moved_prism`).

``--without displacement clocks gm rocking ...`` leaves effects of the preset out, to see what each
costs; ``--max-updates N`` runs the joint engine's variance-component loop to at most N
updates (docs/joint.md#the-variance-components-loop). Development seeds are 0-44 (15-44
since 2026-11-30); issue 23's acceptance must be measured on seeds never used (1000-1019
to 5000-5019, by thousands, have been: 6000 on). Prints one line per seed and a Markdown table (docs/simulation.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.checks.verdict import record_verdict
from rtsgt.evaluation import ContinuousGroundTruth
from rtsgt.evaluation.joint_truth import JointGroundTruth
from rtsgt.evaluation.metrics import (
    relative_pose_covariance,
    relative_pose_error_vector,
    rpe_pairs,
    squared_mahalanobis,
)
from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.io.deployment import load_deployment
from rtsgt.joint import engine as joint_engine
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import simulate_deployment, write_deployment
from rtsgt.simulation.compare import compare_to_truth
from rtsgt.simulation.field import white_sigma
from rtsgt.simulation.presets import preset_config

#: Separations of the relative poses, s.
DELTAS_S = (1.0, 10.0, 60.0)


def seeds(text: str) -> list[int]:
    lo, _, hi = text.partition("-")
    return list(range(int(lo), int(hi or lo) + 1))


def continuous(record):
    """The run's ground truth between two times: the per-prism GPs' or the joint engine's."""
    joint = record.computation.joint
    return (ContinuousGroundTruth.from_record(record) if joint is None
            else JointGroundTruth(joint.posterior))


def relative_nees(record, truth_at, delta_s: float) -> np.ndarray:
    """Relative-pose NEES (6 dof) of consecutive ground-truth pairs ``delta_s`` apart."""
    gt = record.groundtruth
    pairs = rpe_pairs(gt.position, gt.t, delta_s, "s")
    pairs = pairs[np.abs(np.diff(gt.t[pairs], axis=1)[:, 0] - delta_s) <= 0.1 * delta_s]
    if pairs.shape[0] == 0:
        return np.zeros(0)
    i, j = pairs.T
    P_i, P_j, cross = continuous(record).pair_covariances(gt.t[i], gt.t[j])
    cov = relative_pose_covariance(gt.rotation[i], gt.position[i], gt.position[j], P_i, P_j,
                                   cross)
    p, q = truth_at(gt.t)
    xi = relative_pose_error_vector(quat_xyzw_to_matrix(q), p, gt.rotation, gt.position, pairs)
    return squared_mahalanobis(xi, cov)


def clocks_within(record, sim) -> float | None:
    """Share of 1 Hz samples of every non-reference station's clock offset against the
    reference (the joint engine's report times, linear between them) within 2 sigma of the
    field truth's; None without clock states."""
    joint = record.computation.joint
    f = sim.truth.field
    if joint is None or not joint.clocks or f is None:
        return None
    inside = []
    for sid, (kn, off, cov) in joint.clocks.items():
        t = np.arange(np.ceil(kn[0]), min(kn[-1], float(record.groundtruth.t[-1])), 1.0)
        W = np.stack([np.interp(t, kn, e) for e in np.eye(kn.size)], axis=1)  # linear between
        ref = f.station_ids.index(record.joint["clock_reference"])
        true = -(f.clock_error_s(f.station_ids.index(sid), t) - f.clock_error_s(ref, t))
        sig = np.sqrt(np.einsum("ti,ij,tj->t", W, cov, W))
        inside.append(np.abs(W @ off - true) < 2 * sig)
    return float(np.mean(np.concatenate(inside)))


def moved_prism(record, sim) -> dict:
    """The prism the field truth moved, those the joint engine found moved and the others'
    hypotheses it carried beside them (docs/joint.md#which-prism-moved), by index, with what
    the stations can see of the move (:func:`move_geometry`); empty without the joint
    engine's prisms or the field truth."""
    joint = record.computation.joint
    f = sim.truth.field
    pf = None if joint is None else joint.prisms
    if pf is None or f is None:
        return {}
    return {"prism_moved": int(f.displaced_prism),
            "prism_found": [int(j) for j in np.flatnonzero(pf.moved)],
            "prism_carried": [int(j) for j in np.flatnonzero((pf.weight > 0) & ~pf.moved)],
            **move_geometry(sim.truth.reference_body, int(f.displaced_prism),
                            np.asarray(f.displacement_body_m, dtype=float))}


def move_geometry(moved: np.ndarray, k: int, delta: np.ndarray) -> dict:
    """What a rigid body's tracked prisms show of one prism's move: prisms at ``moved``
    (P, 3) m after prism ``k`` moved by ``delta`` (3,) m (the survey at ``moved`` less it).
    The inter-prism distances are all the stations see of the body's shape; to first order
    prism ``k``'s move changes those to the others by its projections on their directions,
    and the part of the move orthogonal to them (with three prisms, along their plane's
    normal) is a rotation of the body frame about the other prisms, seen by nothing
    (docs/joint.md#what-no-station-sees). Returns, mm: ``move_mm`` its size,
    ``move_blind_mm`` its part no distance sees (first order), ``move_seen_mm`` the norm of
    the distances' changes (exact) and ``move_other_mm`` the least norm of their changes that
    a move of one other prism leaves unexplained (first order: how far the move is from
    being another prism's)."""
    surveyed = moved.copy()
    surveyed[k] -= delta
    pairs = [(i, j) for i in range(len(moved)) for j in range(i + 1, len(moved))]

    def jac(i: int) -> np.ndarray:  # d (pair distances) / d (prism i's position), (pairs, 3)
        A = np.zeros((len(pairs), 3))
        for n, (a, b) in enumerate(pairs):
            if i in (a, b):
                e = surveyed[a] - surveyed[b]
                A[n] = (1.0 if i == a else -1.0) * e / np.linalg.norm(e)
        return A

    dist = lambda X: np.array([np.linalg.norm(X[a] - X[b]) for a, b in pairs])  # noqa: E731
    change = dist(moved) - dist(surveyed)
    Ak = jac(k)
    seen = np.linalg.pinv(Ak) @ (Ak @ delta)  # the move's part in the row space
    other = [np.linalg.norm(change - jac(i) @ np.linalg.lstsq(jac(i), change, rcond=None)[0])
             for i in range(len(moved)) if i != k]
    return {"move_mm": float(1e3 * np.linalg.norm(delta)),
            "move_blind_mm": float(1e3 * np.linalg.norm(delta - seen)),
            "move_seen_mm": float(1e3 * np.linalg.norm(change)),
            "move_other_mm": float(1e3 * min(other, default=np.inf))}


def deviation_within(record, sim, data) -> float | None:
    """Share of the prisms' deviation coefficients (every harmonic and component the joint
    engine estimates) within 2 sigma of the simulation's (the reality effect's one harmonic,
    ``a sin(k alpha + phi)`` = ``a sin(phi) cos(k alpha) + a cos(phi) sin(k alpha)``, in
    range and across; every other coefficient 0); None without the estimate or the effect."""
    joint = record.computation.joint
    rt = sim.truth.reality
    dev = None if joint is None else joint.deviation
    if dev is None or rt is None or not rt.effects.prism_cyclic:
        return None
    fx = rt.effects
    order = int(round(2.0 * np.pi / fx.prism_cyclic_period_rad))
    truth = np.zeros((len(dev.names), len(dev.orders), 2, 3))  # (prism, order, cos/sin, comp)
    prism_of = {o.station: o.prism for o in data.observations}
    for k, sid in enumerate(rt.station_ids):
        if order not in dev.orders or sid not in prism_of:
            continue
        i, o = dev.names.index(prism_of[sid]), dev.orders.index(order)
        for comp, amp in ((0, fx.prism_cyclic_range_m), (1, fx.prism_cyclic_across_m)):
            phi = rt.prism_phase_rad[k, comp]
            truth[i, o, :, comp] = amp * np.sin(phi), amp * np.cos(phi)
    z = (dev.coef - truth.reshape(dev.coef.shape)) / dev.sigma
    return float(np.mean(np.abs(z) < 2.0))


def gm_z(record, sim) -> list[float] | None:
    """The Gauss-Markov noise's determined components (each station's and channel's sigma and
    correlation time) against the field truth's, in their sigmas (in log); None without the
    estimate."""
    joint = record.computation.joint
    f = sim.truth.field
    fit = None if joint is None else joint.gauss_markov
    if fit is None or f is None:
        return None
    z = []
    for i, sid in enumerate(fit.stations):
        k = f.station_ids.index(sid)
        for c in range(3):
            if not fit.determined[i, c] or f.gm_sigma[k, c] <= 0:
                continue
            z.append(np.log(fit.sigma[i, c] / f.gm_sigma[k, c]) / fit.sd_log[i, c, 0])
            z.append(np.log(fit.tau_s[i, c] / f.gm_tau_s[k, c]) / fit.sd_log[i, c, 1])
    return [float(x) for x in z]


def white_z(record, sim) -> list[float] | None:
    """The white noise's determined channels (each station's Hz, V, d): the variance at the
    station's median range against the field truth's there
    (:func:`rtsgt.simulation.field.white_sigma` squared), in its sigmas; None without the
    estimate."""
    joint = record.computation.joint
    f = sim.truth.field
    fit = None if joint is None else joint.noise
    if fit is None or f is None or fit.median_basis is None:
        return None
    v, sd = fit.median_variance()
    z = []
    for i, sid in enumerate(fit.stations):
        k = f.station_ids.index(sid)
        d = fit.median_range_m[i]
        truth = white_sigma(np.array([d]), f.white[k], f.range_coef[k])[0] ** 2
        on = fit.determined[i, :, 0] & (sd[i] > 0)
        z.extend((v[i, on] - truth[on]) / sd[i, on])
    return [float(x) for x in z]


def within(z: list[float] | None) -> float | None:
    """Share of ``z`` within 2 (None where there is none)."""
    return float(np.mean(np.abs(z) < 2.0)) if z else None


def config(args):
    """The preset's configuration, less the effects ``--without`` names, with the rocking's
    speed exponent of ``--rocking-exponent``."""
    cfg = preset_config("field-hour", duration_s=args.duration)
    fx, rx = cfg.field, cfg.reality
    for name in args.without:
        if name == "displacement":
            fx = dataclasses.replace(fx, prism_displacement_m=(0.0, 0.0))
        elif name == "gm":
            fx = dataclasses.replace(fx, angle_gm_rad=(0.0, 0.0), distance_gm_m=(0.0, 0.0))
        elif name == "rocking":
            fx = dataclasses.replace(fx, rocking_angle_rad=(0.0, 0.0), rocking_shift_m=(0.0, 0.0),
                                     rocking_heave_m=(0.0, 0.0))
        elif name == "clocks":
            fx = dataclasses.replace(fx, clock_drift_s_per_h=(0.0, 0.0),
                                     clock_walk_s_per_sqrt_h=0.0)
        else:
            rx = dataclasses.replace(rx, **{name: False})
    if args.rocking_exponent is not None:
        fx = dataclasses.replace(fx, rocking_speed_exponent=args.rocking_exponent)
    return dataclasses.replace(cfg, field=fx, reality=rx)


def one(seed: int, args, tmp: Path) -> dict:
    sim = simulate_deployment(config(args), seed)
    data, options = load_deployment(write_deployment(sim, tmp / f"field-{seed}"))
    if args.prism_stability_mm is not None:
        data = dataclasses.replace(data, reference=dataclasses.replace(
            data.reference, stability=1e-3 * args.prism_stability_mm))
    options = options.updated(seed=seed, **({"engine": args.engine} if args.engine else {}))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        start = time.perf_counter()
        rec = run_pipeline(data, options)
        wall = time.perf_counter() - start
        gt = rec.groundtruth
        p, q = sim.truth_at(gt.t)
        c = compare_to_truth(gt, p, q, split=rec.groundtruth_split)
        rel = {f"{d:g}s": relative_nees(rec, sim.truth_at, d) for d in DELTAS_S}
    ip = rec.self_checks["inter_prism_distances"].get("overall") or {}
    n6 = c.nees_pose
    verdict = record_verdict(rec)
    raw = (rec.self_checks.get("raw_block_cv") or {}).get("overall") or {}
    return {
        **moved_prism(rec, sim),
        "clocks_within_2sigma": clocks_within(rec, sim),
        "deviation_within_2sigma": deviation_within(rec, sim, data),
        "gm_z": (zg := gm_z(rec, sim)), "gm_within_2sigma": within(zg),
        "white_z": (zw := white_z(rec, sim)), "white_within_2sigma": within(zw),
        "raw_block_cv": raw.get("nees_per_dof"),
        "seed": seed, "poses": len(gt), "wall_s": wall,
        "knots": (rec.joint or {}).get("knots"),  # the joint engine's (its memory's size)
        "nees6": n6.mean / 6, "in95": float(np.mean(n6.values <= chi2.ppf(0.95, 6))),
        "split_consistent": bool(n6.consistent),
        "rel": {k: (float(v.mean() / 6) if v.size else None, int(v.size))
                for k, v in rel.items()},
        "rel_values": rel,
        "z2": ip.get("mean_z2"), "z2_interval": ip.get("interval_95"),
        "verdict": verdict.level, "reasons": [f.check for f in verdict.reasons],
        "sigma_mm": float(1e3 * np.median(np.sqrt(np.trace(gt.cov[:, :3, :3], axis1=1,
                                                           axis2=2)))),
        "error_mm": float(1e3 * np.median(np.linalg.norm(gt.position - p, axis=1))),
        "n6_values": n6.values,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="0-4", help="first-last (inclusive)")
    ap.add_argument("--duration", type=float, default=None,
                    help="s (default: the preset's, 3600)")
    ap.add_argument("--engine", default=None, help="pose engine (default: the deployment's)")
    ap.add_argument("--without", nargs="*", default=[],
                    choices=["displacement", "clocks", "gm", "rocking", "prism_cyclic",
                             "tripod_settling"],
                    help="effects of the preset to leave out (to see what each costs)")
    ap.add_argument("--rocking-exponent", type=float, default=None,
                    help="the rocking's size while driving as (v / top speed) ** this "
                         "(default: the preset's, 1; 0: one size, as on the real deployments)")
    ap.add_argument("--max-updates", type=int, default=None,
                    help="the joint engine's variance-component updates at most (default: "
                         "its VCE_MAX_ITER; docs/joint.md#the-variance-components-loop)")
    ap.add_argument("--prism-stability-mm", type=float, default=None,
                    help="the deployment's [reference] prism_stability_mm (default: its own, "
                         "0; docs/joint.md#what-no-station-sees)")
    ap.add_argument("--out", default=None,
                    help="folder: each seed's result as <seed>.json when it is done")
    args = ap.parse_args()
    if args.max_updates is not None:  # a benchmark's knob: the loop's stop, read at the call
        joint_engine.VCE_MAX_ITER = args.max_updates
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds(args.seeds):
            r = one(seed, args, Path(tmp))
            rows.append(r)
            line = json.dumps({k: v for k, v in r.items() if not k.endswith("values")})
            print(line, flush=True)
            if args.out:
                Path(args.out).mkdir(parents=True, exist_ok=True)
                (Path(args.out) / f"{seed}.json").write_text(json.dumps(
                    {**json.loads(line), "n6_values": r["n6_values"].tolist(),
                     "rel_values": {k: v.tolist() for k, v in r["rel_values"].items()}}))
    table(rows)


def _f(v, fmt: str = ".2f") -> str:
    return "-" if v is None else format(v, fmt)


#: The shares of estimated parameters within 2 sigma of the truth: key, column title.
SHARES = (("clocks_within_2sigma", "clocks"), ("deviation_within_2sigma", "deviation"),
          ("gm_within_2sigma", "Gauss-Markov"), ("white_within_2sigma", "white"))


def _shares(values) -> str:
    """Each of :data:`SHARES`' values (None or a list of per-seed shares, pooled) in %."""
    out = []
    for v in values:
        v = [x for x in (v if isinstance(v, list) else [v]) if x is not None]
        out.append(_f(100 * np.mean(v) if v else None, ".1f"))
    return " | ".join(out)


def table(rows: list[dict]) -> None:
    """The Markdown table of the seeds' results and their pooled line."""
    titles = " | ".join(f"{t} in 2 sigma" for _, t in SHARES)
    print("\n| seed | poses | pose NEES/dof | in 95 % | split test | rel. NEES/dof 1 s | 10 s "
          f"| 60 s | inter-prism z^2 (accepted) | raw block CV | {titles} "
          "| verdict | median sigma mm | median error mm | run s |")
    print("|---|---:|---:|---:|---|---:|---:|---:|---|---:|" + "---:|" * len(SHARES)
          + "---|---:|---:|---:|")
    for r in rows:
        rel = " | ".join(_f(r["rel"][k][0]) for k in r["rel"])
        lo, hi = r["z2_interval"] or (np.nan, np.nan)
        z2 = "-" if r["z2"] is None else f"{r['z2']:.2f} ({lo:.2f}-{hi:.2f})"
        print(f"| {r['seed']} | {r['poses']} | {r['nees6']:.2f} | {100 * r['in95']:.1f} % | "
              f"{'consistent' if r['split_consistent'] else 'rejected'} | {rel} | {z2} | "
              f"{_f(r.get('raw_block_cv'))} | {_shares(r.get(k) for k, _ in SHARES)} | "
              f"{r['verdict']} | {r['sigma_mm']:.2f} | {_f(r.get('error_mm'))} | "
              f"{r['wall_s']:.0f} |")
    n6 = np.concatenate([np.asarray(r["n6_values"]) for r in rows])
    rel = " | ".join(_f(np.concatenate([np.asarray(r["rel_values"][k]) for r in rows]).mean() / 6)
                     for k in rows[0]["rel"])
    z2 = [r["z2"] for r in rows if r["z2"] is not None]
    raw = [r["raw_block_cv"] for r in rows if r.get("raw_block_cv") is not None]
    print(f"| pooled | {n6.size} | {n6.mean() / 6:.2f} | "
          f"{100 * np.mean(n6 <= chi2.ppf(0.95, 6)):.1f} % | "
          f"{sum(r['split_consistent'] for r in rows)} of {len(rows)} | {rel} | "
          f"{_f(np.mean(z2) if z2 else None)} | {_f(np.mean(raw) if raw else None)} | "
          f"{_shares([r.get(k) for r in rows] for k, _ in SHARES)} | "
          f"{sum(r['verdict'] == 'not usable as is' for r in rows)} not usable | "
          f"{np.median([r['sigma_mm'] for r in rows]):.2f} | "
          f"{_f(np.median([r['error_mm'] for r in rows]))} | "
          f"{np.mean([r['wall_s'] for r in rows]):.0f} |")


if __name__ == "__main__":
    main()
