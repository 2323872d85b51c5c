"""What a noise source is: its name, its kind, and its first-order covariance.

A source is a small class registered in :mod:`rtsgt.noise.sources`; how to add one:
docs/noise-model.md#adding-a-noise-source.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.noise.packed import packed_outer


@dataclass(frozen=True)
class FirstOrder:
    """What the first-order terms of one set of observations are built from (N points).

    ``nom`` the validated nominal quantities (:class:`rtsgt.noise.model.Nominal`), ``model``
    the :class:`rtsgt.noise.model.NoiseModel`; ``j_hz``, ``j_v`` the polar Jacobian's angle
    columns and ``u`` the unit line of sight, world axes, (3, N), m/rad and 1;
    ``T_world_station`` the station's transform or None.
    """

    nom: object
    model: object
    j_hz: np.ndarray
    j_v: np.ndarray
    u: np.ndarray
    T_world_station: object = None

    @property
    def n(self) -> int:
        """Number of points N."""
        return self.u.shape[1]

    def outer(self, terms) -> np.ndarray:
        """Packed ``sum w v v^T`` (6, N) of ``(v, w)`` terms (:func:`packed_outer`)."""
        return packed_outer(terms, self.n)


class NoiseSource:
    """One error of the measurement model (docs/noise-model.md#the-perturbed-measurement).

    Class attributes: ``name`` (the key of ``PrismTrack.cov_by_source`` and of the TOML's
    ``[noise] sources``), ``label`` (for tables and figures), ``white`` (independent from one
    measurement to the next: given to the GP; else systematic, added after it) and
    ``displaces_reading`` (perturbs the measured positions the velocity is differenced from).
    """

    name: str = ""
    label: str = ""
    white: bool = False
    displaces_reading: bool = False

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """The source's first-order covariance, world frame, packed (6, N), m^2."""
        raise NotImplementedError
