"""A rigid transform given on the command line: seven numbers, or a file holding it.

``rtsgt evaluate --mounting`` takes ``T_body_sensor`` (the sensor's pose in the body frame,
:mod:`rtsgt.evaluation.mounting`) in one of these forms:

- ``x,y,z,qx,qy,qz,qw`` on the command line (metres, a unit quaternion, scalar last: the TUM
  order);
- a JSON file with the keys ``x, y, z, qx, qy, qz, qw`` (evo's transform files, as for
  ``evo_traj --transform_right``);
- a text file with the 16 numbers of the 4x4 matrix (row by row, whitespace or commas), or the
  seven numbers above.

The quaternion (or the matrix's rotation) must be unit (orthonormal) within 1e-3.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np

from rtsgt.errors import InputError
from rtsgt.geometry.so3 import matrix_to_quat_xyzw

__all__ = ["TRANSFORM_KEYS", "read_transform"]

#: Keys of a JSON transform file (evo's).
TRANSFORM_KEYS = ("x", "y", "z", "qx", "qy", "qz", "qw")


def _numbers(text: str, source: str) -> np.ndarray:
    parts = [p for p in re.split(r"[\s,;]+", text.strip()) if p]
    try:
        return np.array([float(p) for p in parts], dtype=float)
    except ValueError:
        raise InputError(f"Expected numbers in the transform {source}, got {text.strip()[:60]!r}") from None


def _from_numbers(v: np.ndarray, source: str) -> tuple[float, ...]:
    if not np.all(np.isfinite(v)):
        raise InputError(f"Expected finite numbers in the transform {source}")
    if v.size == 7:
        return tuple(float(x) for x in v)
    if v.size == 16:
        T = v.reshape(4, 4)
        R = T[:3, :3]
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], atol=1e-9):
            raise InputError(f"Expected a last row 0 0 0 1 in the 4x4 transform {source}")
        if not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) <= 0:
            raise InputError(f"Expected a proper rotation in the 4x4 transform {source}")
        return tuple(float(x) for x in np.r_[T[:3, 3], matrix_to_quat_xyzw(R)])
    raise InputError(
        f"Expected 7 numbers (x, y, z, qx, qy, qz, qw) or 16 (a 4x4 matrix) in the transform "
        f"{source}, got {v.size}"
    )


def read_transform(value: str) -> tuple[float, ...]:
    """``(x, y, z, qx, qy, qz, qw)`` of a transform given as text or as a file (module
    docstring). The quaternion is checked by the options that take it.

    Raises
    ------
    InputError
        Not seven numbers, a file that is neither (naming it), a JSON file without the keys.
    """
    path = Path(value)
    if not path.is_file():
        return _from_numbers(_numbers(value, f"{value!r}"), f"{value!r}")
    text = path.read_text(encoding="utf-8")
    if text.lstrip().startswith("{"):
        try:
            obj = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InputError(f"Expected a JSON transform: {exc.msg}", path, exc.lineno) from None
        missing = [k for k in TRANSFORM_KEYS if k not in obj]
        if missing:
            raise InputError(f"Expected the keys {', '.join(TRANSFORM_KEYS)}; missing "
                             f"{', '.join(missing)}", path)
        try:
            v = np.array([float(obj[k]) for k in TRANSFORM_KEYS])
        except (TypeError, ValueError):
            raise InputError("Expected numbers for the keys x, y, z, qx, qy, qz, qw", path) from None
        return _from_numbers(v, f"in {path}")
    lines = [ln.split("#", 1)[0] for ln in text.splitlines()]
    return _from_numbers(_numbers(" ".join(lines), f"in {path}"), f"in {path}")
