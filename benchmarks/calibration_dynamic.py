"""Dynamic and joint self-calibration of the stations against the truth of simulated deployments.

Run: ``python benchmarks/calibration_dynamic.py [--deployments 60] [--duration 600]
[--first-seed 7000] [--models 6dof 4dof] [--samples 500] [--mc 5] [--step 0.5]``

For every deployment ``first_seed + k`` (:mod:`rtsgt.simulation`, written as files and read
back), the pipeline's own calibration inputs are built (:func:`rtsgt.pipeline.calibration_samples`:
module 1, the tracks in the stations' frames, module 2, the GPs, the samples), and the stations
are calibrated three ways under each model: from the GCPs (:func:`rtsgt.calibration.calibrate`,
its Monte Carlo), from the robot's motion (``dynamic``) and from both (``joint``)
(:func:`rtsgt.calibration.dynamic.calibrate_dynamic`, linear covariance). Against the true
``T_world_station`` and clock offsets it reports, pooled over the deployments:

- NEES / dof of the non-reference stations' poses, all stations jointly (the 6 components
  under ``6dof``; x, y, z and the yaw under ``4dof``): 1 if the covariance is honest, and
  the share of deployments inside the 95 % region;
- the same with the relative clock offsets (dynamic, joint), and the clock offsets' mean
  ``z^2``;
- the ratio of the joint calibration's sigma to the GCPs' (per station, ``sqrt`` of the
  trace of the position block; and of the yaw), its median over stations and deployments:
  against the GCP calibration (its Kabsch fit and Monte Carlo), and against the GCPs'
  generalised least-squares fit alone (``gcp_gls``: the joint fit without the distances,
  which weights each shot by its full covariance), which separates the distances' gain from
  the weighting's;
- the deployments the dynamic fit refuses (the trajectory does not determine the stations),
  and the timings.

``--mc N`` also runs the Monte Carlo engine (``--samples`` refits) on the first N deployments
and reports the ratio of its sigmas to the linear ones.
"""

from __future__ import annotations

import argparse
import tempfile
import time
import warnings
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.calibration import calibrate
from rtsgt.calibration.dynamic import SAMPLE_STEP_S, calibrate_dynamic
from rtsgt.calibration.gcp import gcp_atmospheric_correction
from rtsgt.errors import GeometryError
from rtsgt.filtering import module1
from rtsgt.geometry.transform import perturbation
from rtsgt.io.deployment import load_deployment
from rtsgt.noise import NoiseModel
from rtsgt.pipeline import calibration_samples
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment

#: The components compared under each model (x, y, z, rx, ry, rz).
COMPONENTS = {"6dof": [0, 1, 2, 3, 4, 5], "4dof": [0, 1, 2, 5]}


def _stacked(result, stations):
    """Stacked left perturbations' covariance of ``stations`` (and the clocks, when the fit
    has them): the dynamic fit's own, or the GCP calibration's from its samples."""
    if result.dynamic is not None:
        return result.dynamic.covariance
    xi = [perturbation(result.transforms[s].rotation, result.transforms[s].translation,
                       result.transforms[s].samples_rotation,
                       result.transforms[s].samples_translation) for s in stations]
    return np.cov(np.concatenate(xi, axis=1), rowvar=False)


def _scores(result, sim, model: str) -> dict:
    """NEES of the stations' poses (and with the clocks), clock z, position and yaw sigmas."""
    truth = sim.truth
    ref = result.reference_station
    stations = [s for s in result.transforms if s != ref]
    e = np.concatenate([perturbation(truth.T_world_station[s].rotation,
                                     truth.T_world_station[s].translation,
                                     result.transforms[s].rotation,
                                     result.transforms[s].translation) for s in stations])
    C = _stacked(result, stations)
    idx = np.concatenate([6 * k + np.array(COMPONENTS[model]) for k in range(len(stations))])
    out = {"nees": float(e[idx] @ np.linalg.solve(C[np.ix_(idx, idx)], e[idx])),
           "dof": idx.size,
           "sigma_pos": [float(np.sqrt(np.trace(result.transforms[s].covariance[:3, :3])))
                         for s in stations],
           "sigma_yaw": [float(np.sqrt(result.transforms[s].covariance[5, 5]))
                         for s in stations]}
    if result.dynamic is not None and result.dynamic.clock_offset_s:
        fit = result.dynamic
        clk = np.array([fit.clock_offset_s[s] - (truth.clock_offset_s[s]
                                                 - truth.clock_offset_s[ref])
                        for s in fit.clock_offset_s])
        full = np.concatenate([e, clk])
        jdx = np.concatenate([idx, 6 * len(stations) + np.arange(clk.size)])
        out["nees_clock"] = float(full[jdx] @ np.linalg.solve(C[np.ix_(jdx, jdx)], full[jdx]))
        out["dof_clock"] = jdx.size
        out["clock_z"] = (clk / np.array(list(fit.clock_sigma_s.values()))).tolist()
        out["variance_factor"] = fit.variance_factor
    return out


def deployment(seed: int, duration: float, models, samples: int, mc: bool, tmp: Path,
               step: float = SAMPLE_STEP_S) -> dict:
    sim = simulate_deployment(SimulationConfig(duration_s=duration), np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, tmp / f"dep{seed}"))
    opts = opts.updated(seed=seed, samples=samples)
    model = NoiseModel(instrument=data.instrument)
    out: dict = {"seed": seed, "time": {}}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # markers seen by one station, by design
        filtered = [module1(o, opts.filter)[0] for o in data.observations]
        t0 = time.perf_counter()
        smp = calibration_samples(data, filtered, model, opts, step)
        out["time"]["samples"] = time.perf_counter() - t0
        gcp = gcp_atmospheric_correction(data.gcp, model, data.weather,
                                         min(float(o.t[0]) for o in filtered))
        for m in models:
            kw = {"reference_station": data.reference_station, "instrument": data.instrument,
                  "model": m}
            rng = np.random.default_rng(seed)
            res = {"gcp": calibrate(gcp, samples=samples, rng=rng, **kw)}
            gcp0 = calibrate(gcp, samples=0, **kw)
            res["gcp_gls"] = calibrate_dynamic(None, gcp=gcp, gcp_calibration=gcp0,
                                               n_samples=samples, rng=rng, **kw)
            t0 = time.perf_counter()
            try:
                res["dynamic"] = calibrate_dynamic(smp, n_samples=samples, rng=rng, **kw)
            except GeometryError as exc:
                out[f"{m}_refused"] = str(exc)
            out["time"][f"{m}_dynamic"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            res["joint"] = calibrate_dynamic(smp, gcp=gcp, rng=rng, n_samples=samples,
                                             gcp_calibration=gcp0, **kw)
            out["time"][f"{m}_joint"] = time.perf_counter() - t0
            for name, r in res.items():
                out[f"{m}_{name}"] = _scores(r, sim, m)
            if mc and "dynamic" in res:
                t0 = time.perf_counter()
                r_mc = calibrate_dynamic(smp, engine="mc", n_samples=samples, rng=rng, **kw)
                out["time"][f"{m}_dynamic_mc"] = time.perf_counter() - t0
                out[f"{m}_mc_ratio"] = [
                    float(np.sqrt(r_mc.transforms[s].covariance[k, k]
                                  / res["dynamic"].transforms[s].covariance[k, k]))
                    for s in r_mc.dynamic.stations for k in COMPONENTS[m]]
    return out


def summary(rows: list[dict], models) -> None:
    for m in models:
        print(f"\nmodel {m}")
        print(f"{'method':<8} {'deployments':>11} {'NEES/dof':>9} {'in 95%':>7} "
              f"{'+clocks':>8} {'clock z^2':>9} {'median sigma pos mm':>20}")
        for name in ("gcp", "gcp_gls", "dynamic", "joint"):
            got = [r[f"{m}_{name}"] for r in rows if f"{m}_{name}" in r]
            if not got:
                continue
            nees = np.array([g["nees"] for g in got])
            dof = got[0]["dof"]
            inside = np.mean(nees <= chi2.ppf(0.95, dof))
            line = (f"{name:<8} {len(got):>11d} {nees.sum() / (dof * len(got)):>9.3f} "
                    f"{inside:>7.3f}")
            if "nees_clock" in got[0]:
                nc = sum(g["nees_clock"] for g in got) / sum(g["dof_clock"] for g in got)
                cz = np.mean(np.concatenate([g["clock_z"] for g in got]) ** 2)
                line += f" {nc:>8.3f} {cz:>9.3f}"
            else:
                line += f" {'':>8} {'':>9}"
            sig = np.concatenate([g["sigma_pos"] for g in got]) * 1e3
            print(line + f" {np.median(sig):>20.2f}")
        both = [r for r in rows if f"{m}_joint" in r]
        ratio_p = np.concatenate([np.array(r[f"{m}_joint"]["sigma_pos"])
                                  / np.array(r[f"{m}_gcp"]["sigma_pos"]) for r in both])
        ratio_y = np.concatenate([np.array(r[f"{m}_joint"]["sigma_yaw"])
                                  / np.array(r[f"{m}_gcp"]["sigma_yaw"]) for r in both])
        print(f"joint / GCP sigma, median over stations: position {np.median(ratio_p):.3f} "
              f"(max {ratio_p.max():.3f}), yaw {np.median(ratio_y):.3f}")
        ratio_g = np.concatenate([np.array(r[f"{m}_joint"]["sigma_pos"])
                                  / np.array(r[f"{m}_gcp_gls"]["sigma_pos"]) for r in both])
        ratio_gy = np.concatenate([np.array(r[f"{m}_joint"]["sigma_yaw"])
                                   / np.array(r[f"{m}_gcp_gls"]["sigma_yaw"]) for r in both])
        print(f"joint / GCP least-squares sigma: position {np.median(ratio_g):.3f} "
              f"(max {ratio_g.max():.3f}), yaw {np.median(ratio_gy):.3f}")
        dyn = [r for r in rows if f"{m}_dynamic" in r]
        if dyn:
            ratio_d = np.concatenate([np.array(r[f"{m}_dynamic"]["sigma_pos"])
                                      / np.array(r[f"{m}_gcp"]["sigma_pos"]) for r in dyn])
            print(f"dynamic / GCP sigma, median over stations: position {np.median(ratio_d):.3f}")
        refused = [r["seed"] for r in rows if f"{m}_refused" in r]
        print(f"dynamic refused on {len(refused)} of {len(rows)} deployments"
              + (f" (seeds {', '.join(map(str, refused))})" if refused else ""))
        vf = [r[f"{m}_dynamic"]["variance_factor"] for r in dyn]
        if vf:
            print(f"dynamic variance factor: median {np.median(vf):.3f}, "
                  f"range {min(vf):.3f}-{max(vf):.3f}")
        mc = [r[f"{m}_mc_ratio"] for r in rows if f"{m}_mc_ratio" in r]
        if mc:
            a = np.concatenate(mc)
            print(f"Monte Carlo / linear sigma over {len(mc)} deployments: median {np.median(a):.3f}, "
                  f"range {a.min():.3f}-{a.max():.3f}")
    times = {k: np.median([r["time"][k] for r in rows if k in r["time"]])
             for k in rows[0]["time"]}
    print("\nmedian times, s: " + ", ".join(f"{k} {v:.1f}" for k, v in times.items()))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--deployments", type=int, default=60)
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--first-seed", type=int, default=7000)
    ap.add_argument("--models", nargs="+", default=["6dof", "4dof"])
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--mc", type=int, default=5)
    ap.add_argument("--step", type=float, default=SAMPLE_STEP_S,
                    help="time between the samples of the tracks, s")
    args = ap.parse_args(argv)
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        for k in range(args.deployments):
            seed = args.first_seed + k
            rows.append(deployment(seed, args.duration, args.models, args.samples,
                                   k < args.mc, Path(tmp), args.step))
            r = rows[-1]
            print(f"seed {seed}: " + ", ".join(
                f"{m} {n} {r[f'{m}_{n}']['nees'] / r[f'{m}_{n}']['dof']:.2f}"
                for m in args.models for n in ("gcp", "gcp_gls", "dynamic", "joint")
                if f"{m}_{n}" in r), flush=True)
    print(f"\n{args.deployments} deployments x {args.duration:g} s, seeds "
          f"{args.first_seed}-{args.first_seed + args.deployments - 1}, "
          f"{time.perf_counter() - t0:.0f} s")
    summary(rows, args.models)


if __name__ == "__main__":
    main()
