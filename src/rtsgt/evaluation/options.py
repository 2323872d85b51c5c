"""Options of an evaluation (one owner of their defaults and of the rule they meet).

:func:`rtsgt.evaluation.evaluate` and ``rtsgt evaluate`` both map onto
:class:`EvaluationOptions`; its ``__post_init__`` is the one check every value meets.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rtsgt.choices import DEFAULT_MAX_DT_S  # for a ground truth without a gap limit
from rtsgt.errors import InputError
from rtsgt.evaluation.align import ALIGN_METHODS
from rtsgt.evaluation.metrics import DELTA_UNITS
from rtsgt.evaluation.mounting import JOINT_ALIGNMENTS, parse_estimate

__all__ = ["EvaluationOptions", "DEFAULT_MAX_DT_S"]


@dataclass(frozen=True)
class EvaluationOptions:
    """How an estimate is associated, aligned and compared (evo's options; docs/evaluation.md).

    ``align`` (:data:`~rtsgt.evaluation.align.ALIGN_METHODS`), ``n_align``, ``weighted``; RPE pairs
    ``delta``, ``delta_unit`` (m, s, f), ``all_pairs``, ``rel_delta_tol``,
    ``pairs_from_reference``; ``time_offset`` s; ``max_dt`` s (also the RPE gap warning's limit);
    ``estimate`` any of rotation, lever, lever-xy, clock (mounting, all; a comma-separated string
    accepted, stored in :data:`~rtsgt.evaluation.mounting.MOUNTING_PARAMETERS` order);
    ``mounting`` the given ``T_body_sensor`` as ``(x, y, z, qx, qy, qz, qw)`` (None: identity).
    InputError for a value outside its rule.
    """

    align: str = "se3"
    n_align: int | None = None
    weighted: bool = False
    delta: float = 1.0
    delta_unit: str = "m"
    all_pairs: bool = False
    rel_delta_tol: float = 0.1
    pairs_from_reference: bool = False
    time_offset: float = 0.0
    max_dt: float | None = DEFAULT_MAX_DT_S
    estimate: tuple[str, ...] | str = ()
    mounting: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        if self.align not in ALIGN_METHODS:
            raise InputError(f"Expected an alignment in {ALIGN_METHODS}, got {self.align!r}")
        if self.n_align is not None and (
            int(self.n_align) != self.n_align or self.n_align < 1
        ):
            raise InputError(f"Expected a positive integer n_align, got {self.n_align}")
        if self.delta_unit not in DELTA_UNITS:
            raise InputError(f"Expected a delta unit in {DELTA_UNITS}, got {self.delta_unit!r}")
        if not (np.isfinite(self.delta) and self.delta > 0):
            raise InputError(f"Expected a positive RPE delta, got {self.delta}")
        if self.delta_unit == "f" and float(self.delta) != int(self.delta):
            raise InputError(f"Expected an integer RPE delta in frames, got {self.delta}")
        if not (np.isfinite(self.rel_delta_tol) and self.rel_delta_tol >= 0):
            raise InputError(f"Expected a finite rel_delta_tol >= 0, got {self.rel_delta_tol}")
        if not np.isfinite(self.time_offset):
            raise InputError(f"Expected a finite time offset, got {self.time_offset}")
        if self.max_dt is not None and not self.max_dt > 0:
            raise InputError(f"Expected a positive max_dt, got {self.max_dt}")
        object.__setattr__(self, "estimate", parse_estimate(self.estimate))
        if self.estimate and self.align not in JOINT_ALIGNMENTS:
            raise InputError(
                f"Expected an alignment in {JOINT_ALIGNMENTS} to estimate "
                f"{', '.join(self.estimate)}, got {self.align!r}"
            )
        if self.mounting is not None:
            object.__setattr__(self, "mounting", _mounting(self.mounting))


def _mounting(value) -> tuple[float, ...]:
    """``(x, y, z, qx, qy, qz, qw)`` checked: finite, a unit quaternion within 1e-3
    (renormalised, ``qw >= 0``)."""
    try:
        m = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError(f"Expected a mounting (x, y, z, qx, qy, qz, qw), got {value!r}") from None
    if m.size != 7 or not np.all(np.isfinite(m)):
        raise InputError(
            f"Expected a mounting of 7 finite numbers (x, y, z, qx, qy, qz, qw), got {value!r}"
        )
    norm = float(np.linalg.norm(m[3:]))
    if abs(norm - 1.0) > 1e-3:
        raise InputError(f"Expected a unit mounting quaternion, got norm {norm:.6g}")
    q = m[3:] / norm
    if q[3] < 0:
        q = -q
    return tuple(float(v) for v in np.r_[m[:3], q])
