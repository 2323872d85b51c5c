"""The joint engine (issue 23, steps 2 and 2b) against the per-prism linear engine on
simulated deployments: NEES/dof, 95 % coverage, median sigma ratio, iterations, wall time and
traced peak memory of the joint solve; with ``--field`` the ``field-hour`` preset and the
clock states (offsets against the truth at 1 Hz: share within 2 sigma). Numbers:
docs/joint.md#measured.

Usage: python benchmarks/joint.py [--duration 600] [--seeds 101 102 103] [--time-sync]
       [--field [--without displacement gm reality survey]] [--clocks] [--prisms] [--noise]
"""

from __future__ import annotations

import argparse
import tempfile
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from rtsgt.geometry.so3 import quat_xyzw_to_matrix
from rtsgt.geometry.transform import perturbation
from rtsgt.io.deployment import load_deployment
from rtsgt.joint import estimate_joint
from rtsgt.joint.knots import qc_from_prisms
from rtsgt.joint.measurements import GLOBAL_SOURCES, polar_measurements
from rtsgt.joint.noise import CHANNELS, RANGE_UNIT_M, noise_basis
from rtsgt.pipeline import run_pipeline
from rtsgt.simulation import SimulationConfig, simulate_deployment, write_deployment
from rtsgt.simulation.presets import preset_config
from rtsgt.simulation.reality import RealityEffects


def clock_scores(jr, sim, t: np.ndarray) -> dict:
    """Share of 1 Hz samples of each station's offset within 2 sigma of the field truth."""
    f = sim.truth.field
    ref = f.clock_error_s(0, t)
    within, z2 = [], []
    for sid, (kn, off, cov) in jr.clocks.items():
        W = np.stack([np.interp(t, kn, e) for e in np.eye(kn.size)], axis=1)  # linear between
        sig = np.sqrt(np.einsum("ti,ij,tj->t", W, cov, W))
        z = (W @ off + (f.clock_error_s(f.station_ids.index(sid), t) - ref)) / sig
        within.append(np.abs(z) < 2)
        z2.append(z**2)
    return dict(clock_within_2s=np.mean(np.concatenate(within)),
                clock_z2=np.mean(np.concatenate(z2)))


def field_config(duration_s: float, without: tuple[str, ...] = ()) -> SimulationConfig:
    """The field-hour preset, some of its effects off: ``displacement`` (the moved prism),
    ``gm`` (the Gauss-Markov noise), ``reality`` (settling, the prisms' cyclic error),
    ``survey`` (the survey's noise)."""
    cfg = preset_config("field-hour", duration_s=duration_s)
    fe = cfg.field
    if "displacement" in without:
        fe = replace(fe, prism_displacement_m=(0.0, 0.0))
    if "gm" in without:
        fe = replace(fe, angle_gm_rad=(0.0, 0.0), distance_gm_m=(0.0, 0.0))
    cfg = replace(cfg, field=fe, noise_survey=cfg.noise_survey and "survey" not in without)
    return replace(cfg, reality=RealityEffects()) if "reality" in without else cfg


def prism_scores(jr, sim) -> dict:
    """The prisms found moved, and the displaced prism's estimated shift against the truth's
    (field preset), in its posterior sigmas."""
    pf = jr.prisms
    out = dict(found=",".join(np.array(pf.names)[pf.moved]) or "-",
               shift_sigma=",".join(f"{x:.1f}" for x in pf.shift_sigma))
    f = sim.truth.field  # the poses and the survey are in the robot frame
    if f is not None and np.any(f.displacement_robot_m):
        j = f.displaced_prism
        out.update(moved_prism=pf.names[j],
                   moved_mm=float(np.linalg.norm(f.displacement_robot_m)) * 1e3,
                   shift_err_mm=float(np.linalg.norm(pf.shift[j] - f.displacement_robot_m)) * 1e3,
                   shift_sig_mm=float(np.sqrt(np.trace(pf.cov[3 * j:3 * j + 3, 3 * j:3 * j + 3])))
                   * 1e3)
    return out


def noise_scores(jr, meas, sim) -> dict:
    """The white noise's components per station and channel: the datasheet's variance factor
    and the range part (estimate, sigma); on the field preset each channel's variance at the
    station's median range against the truth's (angles ``w^2 + s^2 d / 100 m``, distance
    ``(w + ppm 1e-6 d)^2``; both over the datasheet's there): share within 2 sigma, |z|."""
    nf = jr.noise
    out = {}
    z = []
    f = sim.truth.field
    for i, sid in enumerate(nf.stations):
        sel = meas.station == i
        for c, ch in enumerate(CHANNELS):
            th, sg, det = nf.theta[i, c], nf.sigma[i, c], nf.determined[i, c]
            out[f"f_{sid}{ch}"] = f"{th[0]:.3g}+-{sg[0]:.2g}" + ("" if det[0] else "(prior)")
            out[f"r_{sid}{ch}"] = f"{np.sqrt(max(th[1], 0)):.2g}" if det[1] else "-"
            if f is None or not sel.any():
                continue
            k = f.station_ids.index(sid)
            d = float(np.median(meas.y[sel, 2]))
            q = noise_basis(np.median(meas.var_white[sel], axis=0)[None, :], np.array([d]))[0, c]
            w, rc = f.white[k, c], f.range_coef[k, c]
            v_true = w**2 + rc**2 * d / RANGE_UNIT_M if c < 2 else (w + 1e-6 * rc * d) ** 2
            g = q * det
            C = nf.cov[i][2 * c:2 * c + 2, 2 * c:2 * c + 2]
            z.append((th @ q - v_true) / np.sqrt(g @ C @ g))
            out[f"t_{sid}{ch}"] = f"{v_true / q[0]:.3g}@{d:.0f}m,z={z[-1]:.1f}"
    if z:
        z = np.abs(np.array(z))
        out.update(noise_within_2s=float(np.mean(z < 2)), noise_max_z=float(z.max()))
    return out


def case(duration_s: float, seed: int, time_sync: bool, folder: Path, field: bool = False,
         clocks: bool = False, without: tuple[str, ...] = (), prisms: bool = False,
         noise: bool = False) -> dict:
    """One simulated deployment through the per-prism pipeline and the joint engine."""
    if field:
        cfg = field_config(duration_s, without)
    else:
        cfg = SimulationConfig(duration_s=duration_s, noise_time_sync=time_sync,
                               noise_survey=False)
    sim = simulate_deployment(cfg, np.random.default_rng(seed))
    data, opts = load_deployment(write_deployment(sim, folder / f"dep{seed}"))
    srcs = tuple(s for s in opts.noise.sources if time_sync or field or s != "time_sync")
    opts = replace(opts.updated(seed=seed, engine="linear"), noise=opts.noise.with_sources(srcs))
    res = run_pipeline(data, opts)
    comp = res.computation
    est, keep = comp.estimate, comp.keep
    tq = comp.prisms.t[keep]
    obs = [o.select(np.isin(o.t, comp.tracks[o.prism].t)) for o in data.observations]
    qc = qc_from_prisms(np.stack([res.qc[p] for p in data.reference.names]), data.reference.xyz)
    tracemalloc.start()
    tick = time.perf_counter()
    jr = estimate_joint(obs, comp.calibration, data.reference, comp.noise_model, tq, tq,
                        est.R[keep], est.t[keep], qc, weather=data.weather, clocks=clocks,
                        prisms=prisms, noise=noise)
    wall = time.perf_counter() - tick
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    p, q = sim.truth_at(tq)
    R_true = quat_xyzw_to_matrix(q)

    def nees(R, t, cov):
        e = perturbation(R_true, p, R, t)
        return np.einsum("ki,kij,kj->k", e, np.linalg.inv(cov), e)

    nj = nees(jr.estimate.R, jr.estimate.t, jr.estimate.cov)
    npp = nees(est.R[keep], est.t[keep], est.cov[keep])
    pos = np.einsum("kii->k", jr.estimate.cov[:, :3, :3])
    pos_pp = np.einsum("kii->k", est.cov[keep][:, :3, :3])
    rot = np.einsum("kii->k", jr.estimate.cov[:, 3:, 3:])
    rot_pp = np.einsum("kii->k", est.cov[keep][:, 3:, 3:])
    c95 = chi2.ppf(0.95, 6)
    extra = clock_scores(jr, sim, np.arange(np.ceil(tq[0]), tq[-1], 1.0)) if field and clocks \
        else {}
    if prisms and jr.prisms is not None:
        extra.update(prism_scores(jr, sim))
    if noise:
        carried = GLOBAL_SOURCES + (("time_sync",) if clocks else ())
        meas = polar_measurements(obs, tuple(comp.calibration.transforms),
                                  tuple(data.reference.names), comp.noise_model, data.weather,
                                  carried)
        extra.update(noise_scores(jr, meas, sim))
    return dict(
        seed=seed, poses=tq.size, knots=jr.n_knots, measurements=jr.n_measurements,
        nees_joint=nj.mean() / 6, nees_pp=npp.mean() / 6,
        cover_joint=np.mean(nj < c95), cover_pp=np.mean(npp < c95),
        ratio_pos=np.median(np.sqrt(pos / pos_pp)), ratio_rot=np.median(np.sqrt(rot / rot_pp)),
        iterations=jr.solve.iterations, converged=jr.solve.converged,
        chi2=jr.chi2_per_dof, wall_s=wall, peak_mib=peak / 2**20, vce=jr.qc.iterations,
        **extra,
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=600.0)
    ap.add_argument("--seeds", type=int, nargs="+", default=[101, 102, 103])
    ap.add_argument("--time-sync", action="store_true",
                    help="the simulator's clock offsets on (the joint engine carries them white)")
    ap.add_argument("--field", action="store_true", help="the field-hour preset")
    ap.add_argument("--clocks", action="store_true", help="the joint engine's clock states")
    ap.add_argument("--prisms", action="store_true",
                    help="the prisms' body positions as parameters (the survey as prior)")
    ap.add_argument("--noise", action="store_true",
                    help="the white noise per station and channel estimated")
    ap.add_argument("--without", nargs="*", default=[],
                    choices=["displacement", "gm", "reality", "survey"],
                    help="field-hour effects left out")
    args = ap.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in args.seeds:
            r = case(args.duration, seed, args.time_sync, Path(tmp), args.field, args.clocks,
                     tuple(args.without), args.prisms, args.noise)
            rows.append(r)
            print(" ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}={v}"
                           for k, v in r.items()), flush=True)
    for key in ("nees_joint", "nees_pp", "cover_joint", "cover_pp", "ratio_pos", "ratio_rot",
                "wall_s", "peak_mib"):
        print(f"{key}: mean {np.mean([r[key] for r in rows]):.3f}")


if __name__ == "__main__":
    main()
