"""The calibration errors shared between stations, and the prisms' joint covariance.

Stations fitted to the same reference shots have correlated calibration errors
(:class:`StationCoupling`); the pose engines take the prisms' joint (3n x 3n) covariance
(:func:`joint_prism_covariance`): docs/pose.md#errors-shared-between-prisms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.geometry.transform import perturbation
from rtsgt.pose.reference import block_diagonal

__all__ = ["StationCoupling", "joint_prism_covariance"]


@dataclass(frozen=True)
class StationCoupling:
    """The correlation of the calibration errors of the stations (their left perturbations
    ``xi``, :mod:`rtsgt.geometry.transform`), from the shared reference shots.

    ``origin``: each station's world position, m (the lever arm of its rotation error);
    ``cross``: ``Cov(xi_a, xi_b)`` (6, 6) for pairs ``a <= b`` (``a == b`` included: one sample
    covariance, so the joint matrix is positive semi-definite), m^2 / m rad / rad^2.
    """

    origin: dict[str, np.ndarray]
    cross: dict[tuple[str, str], np.ndarray]

    @classmethod
    def from_calibration(cls, calib) -> StationCoupling:
        """From the Monte Carlo samples of a :class:`rtsgt.calibration.CalibrationResult`
        (sample m of every station comes from the same perturbed GCP shots)."""
        xi = {}
        for sid, T in calib.transforms.items():
            if T.samples_rotation is None or T.samples_translation is None:
                continue
            d = perturbation(T.rotation, T.translation, T.samples_rotation,
                             T.samples_translation)
            xi[sid] = d - d.mean(axis=0)
        cross = {}
        ids = sorted(xi)
        for i, a in enumerate(ids):
            for b in ids[i:]:  # (a, a) too: the joint matrix is then one sample covariance
                m = xi[a].shape[0]
                if m > 1 and m == xi[b].shape[0]:
                    cross[(a, b)] = xi[a].T @ xi[b] / (m - 1)
        origin = {sid: np.asarray(T.translation, dtype=float)
                  for sid, T in calib.transforms.items()}
        return cls(origin, cross)

    def to_dict(self) -> dict:
        """JSON-ready (pairs keyed ``"a|b"``)."""
        return {"origin_m": {k: v.tolist() for k, v in self.origin.items()},
                "cross_covariance": {f"{a}|{b}": c.tolist() for (a, b), c in self.cross.items()}}

    @classmethod
    def from_dict(cls, doc: dict) -> StationCoupling:
        origin = {str(k): np.asarray(v, dtype=float) for k, v in doc["origin_m"].items()}
        cross = {}
        for key, c in doc["cross_covariance"].items():
            a, b = str(key).split("|")
            cross[(a, b)] = np.asarray(c, dtype=float).reshape(6, 6)
        return cls(origin, cross)

    def block(self, a: str, b: str) -> np.ndarray | None:
        """``Cov(xi_a, xi_b)``, or None when unknown."""
        if (a, b) in self.cross:
            return self.cross[(a, b)]
        if (b, a) in self.cross:
            return self.cross[(b, a)].T
        return None

    def prism_covariance(
        self, xyz_a: np.ndarray, xyz_b: np.ndarray, stations: list[str]
    ) -> np.ndarray:
        """(T, 3n, 3n) calibration part of ``Cov(q(a), q(b))`` for prisms at ``xyz_a``,
        ``xyz_b`` (T, n, 3) m, tracked by ``stations``: block ``(i, j)`` is
        ``J_i(a) Cov(xi_s_i, xi_s_j) J_j(b)^T``, ``J = [I, -[q]x]`` with ``q`` the prism
        relative to its station (as :mod:`rtsgt.noise.sources.calibration`); zero where unknown.
        """
        T, n, _ = xyz_a.shape
        eye = np.broadcast_to(np.eye(3), (T, 3, 3))

        def jac(xyz):
            return [np.concatenate([eye, -hat(xyz[:, i] - self.origin.get(s, np.zeros(3)))],
                                   axis=-1) for i, s in enumerate(stations)]

        Ja, Jb = jac(xyz_a), jac(xyz_b)
        out = np.zeros((T, 3 * n, 3 * n))
        for i in range(n):
            for j in range(n):
                X = self.block(stations[i], stations[j])
                if X is not None:
                    out[:, 3 * i:3 * i + 3, 3 * j:3 * j + 3] = Ja[i] @ X @ np.swapaxes(Jb[j], 1, 2)
        return out


def joint_prism_covariance(
    xyz: np.ndarray, cov: np.ndarray, cov_calibration: np.ndarray, stations: list[str],
    coupling: StationCoupling,
) -> np.ndarray:
    """(T, 3n, 3n) joint covariance of the prisms at ``xyz`` (T, n, 3), m: each prism's total
    ``cov`` (T, n, 3, 3) with its calibration part ``cov_calibration`` replaced, where the
    coupling knows its station, by the joint one of :meth:`StationCoupling.prism_covariance`."""
    known = [coupling.block(s, s) is not None for s in stations]
    rest = np.where(np.array(known)[None, :, None, None], cov - cov_calibration, cov)
    out = block_diagonal(rest) + coupling.prism_covariance(xyz, xyz, stations)
    return 0.5 * (out + np.swapaxes(out, 1, 2))
