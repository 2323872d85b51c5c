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

    ``obs``: one prism by one station, valid (status 0), strictly increasing in time;
    ``model``: the sources and their parameters; ``T_world_station``: the station's transform
    with its 6x6 covariance and/or Monte Carlo samples (None: station frame, no calibration
    source); ``weather``: interpolated at each time (None: the instrument's reference
    atmosphere, 0 ppm); ``engine`` ``"linear"`` or ``"mc"`` (``samples`` per measurement from
    ``rng``, required; ``chunk_size`` measurements per chunk; ``workers`` threads, the result
    does not depend on them; ``mc_dtype`` float32 or float64 working precision,
    docs/noise-model.md#monte-carlo).

    Returns a :class:`~rtsgt.types.PrismTrack`: ``xyz`` (N, 3) m, ``cov`` (N, 3, 3) m^2 and
    ``cov_by_source`` (each source alone), ``range_m``, ``frame``. Raises
    :class:`~rtsgt.errors.InputError` naming the first bad value or argument.
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
