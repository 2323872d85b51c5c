"""The error of the station's transform into the world frame
(docs/noise-model.md#extrinsic-calibration)."""

from __future__ import annotations

import numpy as np

from rtsgt.geometry.so3 import hat
from rtsgt.geometry.transform import perturbation
from rtsgt.noise.packed import SYM, small_matmul
from rtsgt.noise.sources.base import FirstOrder, NoiseSource


def transform_covariance(T_world_station) -> np.ndarray | None:
    """The 6x6 covariance (x, y, z, rx, ry, rz) of a transform, from its samples if needed;
    None without either."""
    if T_world_station is None:
        return None
    if T_world_station.covariance is not None:
        return np.asarray(T_world_station.covariance, dtype=float)
    Rs, ts = T_world_station.samples_rotation, T_world_station.samples_translation
    if Rs is None or ts is None:
        return None
    xi = perturbation(T_world_station.rotation, T_world_station.translation, Rs, ts)
    xi = xi - xi.mean(axis=0)
    return xi.T @ xi / (xi.shape[0] - 1)


def calibration_packed(q: np.ndarray, cov6: np.ndarray) -> np.ndarray:
    """Packed (6, N) ``J_c Sigma_6 J_c^T``, ``J_c = [I, -[q]x]``, for points ``q`` (3, N)
    (``R_world_station p_station``, m) and the transform's 6x6 covariance ``cov6``;
    ``A + B Q + (B Q)^T + Q C Q^T`` as small products (docs/noise-model.md#extrinsic-calibration)."""
    A, B, C = cov6[:3, :3], cov6[:3, 3:], cov6[3:, 3:]
    E = hat(np.eye(3))  # E[l] = [e_l]x
    G = np.einsum("ik,lkj->lij", B, E)  # B E_l, (3, 3, 3)
    H = np.einsum("lik,km,njm->lnij", E, C, E)  # E_l C E_n^T, (3, 3, 3, 3)
    sym_i = [i for i, _ in SYM]
    sym_j = [j for _, j in SYM]
    # packed rows of B Q + (B Q)^T and of Q C Q^T
    GG = (G[:, sym_i, sym_j] + G[:, sym_j, sym_i])  # (3, 6)
    qq = np.stack([q[a] * q[b] for a, b in ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))])
    Hp = H[:, :, sym_i, sym_j]  # (3, 3, 6)
    Hq = np.stack([Hp[0, 0], Hp[1, 1], Hp[2, 2], Hp[0, 1] + Hp[1, 0], Hp[0, 2] + Hp[2, 0],
                   Hp[1, 2] + Hp[2, 1]])  # (6 products, 6 components)
    out = small_matmul(GG.T, q)
    out += small_matmul(Hq.T, qq)
    out += A[sym_i, sym_j][:, None]
    return out


class Calibration(NoiseSource):
    """The transform's left perturbation: Monte Carlo samples or its 6x6 covariance."""

    name = "calibration"
    label = "extrinsic calibration"

    def first_order(self, f: FirstOrder) -> np.ndarray:
        """``J_c Sigma_6 J_c^T`` (zeros without a covariance)."""
        cov6 = transform_covariance(f.T_world_station)
        if cov6 is None:
            return np.zeros((6, f.n))
        return calibration_packed(small_matmul(f.nom.R, f.nom.xyz_station.T), cov6)
