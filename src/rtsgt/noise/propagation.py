"""From the observations of one prism to its track in the world frame, with covariances.

:func:`propagate` runs one of the two engines of the noise model (the Monte Carlo of
:mod:`rtsgt.noise.montecarlo` or the first-order propagation of :mod:`rtsgt.noise.linear`).
"""

from __future__ import annotations

import numpy as np

from rtsgt.errors import InputError
from rtsgt.noise.linear import linear_covariances
from rtsgt.noise.model import NoiseModel, prepare_nominal
from rtsgt.noise.montecarlo import mc_covariances
from rtsgt.types import PrismTrack

__all__ = ["ENGINES", "propagate"]

#: Engines accepted by :func:`propagate`.
ENGINES = ("linear", "mc")

def propagate(
    obs,
    model: NoiseModel,
    *,
    T_world_station=None,
    weather=None,
    engine: str = "linear",
    samples: int = 1000,
    rng: np.random.Generator | None = None,
    chunk_size: int | None = None,
    workers: int = 1,
    mc_dtype=np.float32,
) -> PrismTrack:
    """Positions and covariances of one station's prism observations in the world frame.

    Parameters
    ----------
    obs : Observations
        One prism seen by one station, valid (status 0), strictly increasing in time.
    model : NoiseModel
        Instrument profile, the sources to include and their parameters.
    T_world_station : RigidTransform, optional
        ``T_world_station`` (maps station coordinates into the world frame), with a 6x6
        covariance and/or Monte Carlo samples for the calibration source. None: the result
        is in the station frame and the calibration source is zero.
    weather : WeatherSeries, optional
        Weather for the atmospheric correction, interpolated at each observation time. None:
        the instrument's reference atmosphere (0 ppm).
    engine : {"linear", "mc"}
        First-order propagation, or the paper's Monte Carlo.
    samples : int
        Monte Carlo samples per measurement (``engine="mc"``).
    rng : numpy.random.Generator
        Required by ``engine="mc"``; the result is a deterministic function of its state.
    chunk_size : int, optional
        Measurements per Monte Carlo chunk (memory bound); default keeps ``chunk * samples``
        near 65536.
    workers : int
        Monte Carlo threads (chunks in parallel); the result does not depend on it.
    mc_dtype : {numpy.float32, numpy.float64}
        Working precision of the Monte Carlo samples. The engine samples exact displacements
        from the nominal point, so float32 (the default, about twice as fast) keeps a relative
        precision near 1e-7 on covariances whose Monte Carlo error is 1e-2; the covariances
        are returned in float64 either way.

    Returns
    -------
    PrismTrack
        ``xyz`` (N, 3) nominal positions, m; ``cov`` (N, 3, 3) total covariance, m^2;
        ``cov_by_source`` one (N, 3, 3) entry per source of ``model.sources`` (each with that
        source alone; for the Monte Carlo they add up to the total only approximately);
        ``range_m`` the corrected slope distance; ``frame`` ``T_world_station.frame_to`` or
        ``"station_<id>"``.

    Raises
    ------
    InputError
        NaN or negative distances, zenith angles outside (0, pi), non-increasing times, an
        unknown engine, too few transform samples, ... (naming the value and its index).
    """
    eng = str(engine).lower()
    if eng not in ENGINES:
        raise InputError(f"Unknown noise engine {engine!r}; known: {', '.join(ENGINES)}")
    if not isinstance(model, NoiseModel):
        raise InputError(f"Expected a NoiseModel, got {type(model).__name__}")
    nom = prepare_nominal(obs, model, T_world_station, weather)
    if eng == "mc":
        total, by_source = mc_covariances(
            nom, model, T_world_station, samples=samples, rng=rng, chunk_size=chunk_size,
            workers=workers, dtype=mc_dtype,
        )
    else:
        total, by_source = linear_covariances(nom, model, T_world_station)
    xyz = np.einsum("ij,nj->ni", nom.R, nom.xyz_station) + nom.t_ws  # no BLAS threads
    return PrismTrack(
        t=nom.t,
        xyz=xyz,
        cov=total,
        cov_by_source=by_source,
        prism=obs.prism,
        frame=nom.frame,
        station=obs.station,
        range_m=nom.d_corr,
    )
