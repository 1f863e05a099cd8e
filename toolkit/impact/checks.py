"""Checks of an impact answer before it is given, FE or surrogate.

For every output frame of a whole-face answer (displacement ``(F, N, 3)`` mm, von Mises stress
``(F, N)`` MPa):

- every value is finite;
- the nodes the scene holds (:func:`toolkit.impact.simulate.fixed_nodes`) stay where they are (to
  :data:`FIXED_TOLERANCE_MM`);
- no element is inverted: the smallest scaled Jacobian of the deformed face over all frames is
  above zero (:func:`toolkit.common.meshes.quality.scaled_jacobian`; for tet10 the corner tetrahedron
  scaled by the curved element's Jacobian ratio);
- the von Mises stress is nowhere negative.

:func:`answer_checks` returns the values checked, ``seconds``, ``passed`` and ``problems`` (one
sentence each) without raising; a result's ``summary()["checks"]`` lists them. The FE
(:func:`toolkit.impact.simulate`) raises :class:`~toolkit.common.errors.AnswerError` when its
answer fails them; a surrogate's answer that fails them is flagged (``impact predict``) or replaced
by the FE's (``impact predict --tolerance``).
"""

from __future__ import annotations

import time

import numpy as np

from toolkit.common.errors import AnswerError
from toolkit.common.meshes.mesh import Mesh

__all__ = ["answer_checks", "check_answer", "min_scaled_jacobian_over_frames", "scaled_jacobian_per_frame",
           "FIXED_TOLERANCE_MM"]

#: mm, how far a held node may move (the FE prescribes exactly zero; the surrogate sets it)
FIXED_TOLERANCE_MM = 1e-6


def min_scaled_jacobian_over_frames(face: Mesh, displacement: np.ndarray) -> tuple[float, int]:
    """The smallest element scaled Jacobian of ``face`` moved by each frame of ``displacement``
    ``(F, N, 3)`` mm, and the first frame where it is reached, or where an element first inverts."""
    per_frame = scaled_jacobian_per_frame(face, displacement)
    bad = np.flatnonzero(~(per_frame > 0))
    k = int(bad[0]) if bad.size else int(np.argmin(per_frame))
    return float(per_frame.min()), k


def scaled_jacobian_per_frame(face: Mesh, displacement: np.ndarray) -> np.ndarray:
    """The smallest element scaled Jacobian of ``face`` in each frame of ``displacement``
    ``(F, N, 3)`` mm, ``(F,)``."""
    u = np.asarray(displacement, dtype=float)
    return np.array([face.with_points(face.points + u[k]).scaled_jacobian().min() for k in range(u.shape[0])])


def answer_checks(face: Mesh, displacement: np.ndarray, von_mises: np.ndarray, fixed: np.ndarray) -> dict:
    """The checks of an impact answer (see the module) on the reference ``face``: ``fixed`` (int)
    the held nodes. Returns the values checked (mm, MPa, s), ``passed`` and ``problems``."""
    t0 = time.perf_counter()
    u, vm = np.asarray(displacement, dtype=float), np.asarray(von_mises, dtype=float)
    fixed = np.asarray(fixed, dtype=np.int64)
    problems = []
    finite = bool(np.isfinite(u).all() and np.isfinite(vm).all())
    if not finite:
        problems.append(f"{int((~np.isfinite(u)).any(axis=2).sum() + (~np.isfinite(vm)).sum())} node-frames hold "
                        "NaN or infinite values")
    held = float(np.linalg.norm(u[:, fixed], axis=2).max()) if fixed.size and finite else 0.0
    if held > FIXED_TOLERANCE_MM:
        problems.append(f"held nodes moved up to {held:.3g} mm (expected within {FIXED_TOLERANCE_MM:g} mm)")
    sj, frame = min_scaled_jacobian_over_frames(face, np.nan_to_num(u)) if u.shape[0] else (1.0, 0)
    if not sj > 0:
        problems.append(f"an element first inverts in frame {frame} (minimum scaled Jacobian over the frames "
                        f"{sj:.3g}; expected > 0)")
    lowest = float(np.nanmin(vm)) if vm.size else 0.0
    negative = int((vm < 0).sum())
    if negative:
        problems.append(f"{negative} of {vm.size} node-frames have a negative von Mises stress (lowest {lowest:g} "
                        "MPa; expected >= 0)")
    return {"finite": finite, "held_max_displacement_mm": held, "held_tolerance_mm": FIXED_TOLERANCE_MM,
            "min_scaled_jacobian": sj, "min_scaled_jacobian_frame": frame,
            "inverted_from_frame": None if sj > 0 else frame, "min_von_mises_mpa": lowest,
            "seconds": time.perf_counter() - t0, "passed": not problems, "problems": problems}


def check_answer(face: Mesh, displacement: np.ndarray, von_mises: np.ndarray, fixed: np.ndarray) -> dict:
    """:func:`answer_checks`, raising :class:`AnswerError` when one fails; returns the values checked."""
    checks = answer_checks(face, displacement, von_mises, fixed)
    if not checks["passed"]:
        raise AnswerError("the impact answer failed its checks: " + "; ".join(checks["problems"]), checks)
    return checks
