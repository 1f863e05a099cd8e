"""Surgical plans for orthognathic surgery: rigid motions of the bony segments.

A :class:`SurgicalPlan` holds one :class:`RigidMotion` per bony segment
(:data:`SEGMENTS`: ``lefort``, ``distal``, ``proximal_left``, ``proximal_right``;
segments not given stay put). A motion rotates about its pivot, then translates:
``x' = R (x - pivot) + pivot + t``, everything in mm, axes as in
:mod:`toolkit.common.phantoms.phantom` (``x`` patient's left, ``y`` anterior, ``z`` superior).

The lip-sliding paper (section 2.3.2.2) applies the planned movements in increments: the
intermediate bone positions interpolate the rotation by quaternion slerp from the
identity (short arc) and the translation linearly; :meth:`SurgicalPlan.increments`
gives the cumulative plans at fractions ``1/n, 2/n, ..., 1`` (3 by default).

The proximal mandibular segments rotate about their ipsilateral condyle to follow
the distal mandible (:meth:`SurgicalPlan.with_proximal_following`): the rotation
about the condyle that best maps the proximal bone onto where the distal motion
takes it (least squares, proper rotations only), so the condyles stay in their fossae.

**Validation** runs at construction. Movements beyond the physiological ranges of
the lip-sliding paper (:data:`PHYSIOLOGICAL_RANGES`) warn with :class:`PlanRangeWarning`; beyond
twice the range they raise :class:`PlanError` (a ``ValueError``) unless the plan is built with
``force=True`` (then they warn). NaN never gets in: :class:`RigidMotion` refuses it.

**Files** (``.toml`` or ``.json``): one table per segment with ``translation_mm``,
a rotation (``rotation_quaternion = [w, x, y, z]``, ``rotation_vector_deg`` = axis
times angle in degrees, or ``euler_deg`` = angles about x, y, z applied in that
order) and ``pivot_mm``. ``pivot_mm`` may be left out when the segment does not
rotate, or when the file is read with a phantom, whose segment pivots fill it in
(:meth:`SurgicalPlan.read`); with a phantom, proximal segments absent from the
file follow the distal one. :func:`default_plan` is the packaged typical
bimaxillary plan (``toolkit/static/data/default_plan.toml``) on a phantom.
"""

from __future__ import annotations

import difflib
import json
import math
import tomllib
import warnings
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from toolkit.common import papers
from toolkit.common.errors import ToolkitError
from toolkit.common.meshes.io import atomic_path, read_text

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

    from toolkit.common.phantoms.phantom import FacePhantom
    from toolkit.static.anatomy import FaceAnatomy

__all__ = [
    "MotionRange",
    "PHYSIOLOGICAL_RANGES",
    "SAMPLING_MODES",
    "SAMPLED_SEGMENTS",
    "sampled_parameters",
    "sampling_hull",
    "PLAN_FORMATS",
    "SEGMENTS",
    "PlanError",
    "PlanRangeWarning",
    "RigidMotion",
    "SurgicalPlan",
    "default_plan",
    "dental_arch",
    "jaw_closing",
    "proximal_reference_points",
    "sample_plans",
    "MAX_JAW_CLOSING_MM",
]

SEGMENTS = ("lefort", "distal", "proximal_left", "proximal_right")


class PlanError(ToolkitError, ValueError):
    """A surgical plan, motion or motion range is invalid: an unknown segment or key, NaN, a
    movement beyond twice the physiological range without ``force``, an unreadable plan file."""


@dataclass(frozen=True)
class MotionRange:
    """Range of one segment's movement: ``translation_mm`` (lo, hi) of the pivot's
    displacement in mm and ``rotation_deg`` (lo, hi) of the rotation angle in degrees."""

    translation_mm: tuple[float, float]
    rotation_deg: tuple[float, float]

    def __post_init__(self):
        for name in ("translation_mm", "rotation_deg"):
            lo, hi = (float(v) for v in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo <= hi):
                raise PlanError(f"MotionRange.{name} = {(lo, hi)}; expected 0 <= lo <= hi, finite")
            object.__setattr__(self, name, (lo, hi))


#: segment -> MotionRange of the lip-sliding paper (section 2.3.2.2, measured on its patients): Le Fort I
#: 0-6.3 mm and 0-9.8 degrees, distal mandible 2.1-11.5 mm and 0.5-13.3 degrees.
#: Validation (:meth:`SurgicalPlan.validate`) checks the upper bounds; :func:`sample_plans`
#: draws uniformly between the bounds. The proximal segments have no stated range: they
#: rotate about their condyle to follow the distal one, which at the edge of the distal
#: range takes more than the distal angle but less than twice it in sampled plans, so their
#: bound is twice the distal angle.
PHYSIOLOGICAL_RANGES: Mapping[str, MotionRange] = MappingProxyType(
    {"lefort": MotionRange(papers.LEFORT_TRANSLATION_MM, papers.LEFORT_ROTATION_DEG),
     "distal": MotionRange(papers.DISTAL_TRANSLATION_MM, papers.DISTAL_ROTATION_DEG),
     **{name: MotionRange((0.0, papers.DISTAL_TRANSLATION_MM[1]), (0.0, 2.0 * papers.DISTAL_ROTATION_DEG[1]))
        for name in ("proximal_left", "proximal_right")}}
)
#: directions of sampled movements: ``sagittal`` translations in the y-z plane and rotations
#: about the lateral x axis (the lip-sliding paper's advancements, setbacks, impactions and pitch);
#: ``full`` translation directions and rotation axes uniform on the sphere (yaw and roll too)
SAMPLING_MODES = ("sagittal", "full")
PLAN_FORMATS = (".toml", ".json")
_ROTATION_KEYS = ("rotation_quaternion", "rotation_vector_deg", "euler_deg")
_MOTION_KEYS = ("translation_mm", "pivot_mm") + _ROTATION_KEYS


class PlanRangeWarning(UserWarning):
    """A bony movement lies outside the physiological range of the lip-sliding paper."""


def _vector(value, n: int, name: str) -> np.ndarray:
    """``value`` as a read-only float64 ``(n,)`` array of finite numbers."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise PlanError(f"{name} = {value!r}: expected {n} numbers ({exc})") from exc
    if a.shape != (n,):
        raise PlanError(f"{name} has shape {a.shape}, expected ({n},)")
    if not np.all(np.isfinite(a)):
        raise PlanError(f"{name} = {a.tolist()} holds NaN or inf; expected {n} finite numbers")
    a.flags.writeable = False
    return a


def _quaternion_from_rotvec(rotvec_rad: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation vector (axis times angle, rad)."""
    angle = float(np.linalg.norm(rotvec_rad))
    if angle == 0.0:
        return np.array([1.0, 0.0, 0.0, 0.0])
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) / angle * rotvec_rad])


def _hamilton(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Quaternion product ``a b`` (rotation ``b`` first, then ``a``)."""
    w1, v1, w2, v2 = a[0], a[1:], b[0], b[1:]
    return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])


@dataclass(frozen=True, eq=False, init=False)
class RigidMotion:
    """A rigid motion about a pivot: ``x' = R (x - pivot) + pivot + translation``.

    Constructed from any array-likes of the right length (defaults: the identity about the origin).

    Attributes
    ----------
    rotation : (4,) float, unit quaternion ``(w, x, y, z)``; normalised at
        construction and given the sign with ``w >= 0`` (``q`` and ``-q`` are the
        same rotation), so the rotation angle is in [0, 180] degrees
    translation : (3,) float, mm — the displacement of the pivot
    pivot : (3,) float, mm
    """

    rotation: np.ndarray
    translation: np.ndarray
    pivot: np.ndarray

    def __init__(self, rotation: ArrayLike = (1.0, 0.0, 0.0, 0.0), translation: ArrayLike = (0.0, 0.0, 0.0),
                 pivot: ArrayLike = (0.0, 0.0, 0.0)) -> None:
        q = np.array(_vector(rotation, 4, "rotation quaternion (w, x, y, z)"))
        norm = float(np.linalg.norm(q))
        if norm == 0.0:
            raise PlanError(f"rotation quaternion {q.tolist()} has zero norm; expected a unit quaternion (w, x, y, z)")
        q /= norm
        if q[0] < 0:
            q = -q
        q.flags.writeable = False
        object.__setattr__(self, "rotation", q)
        object.__setattr__(self, "translation", _vector(translation, 3, "translation (mm)"))
        object.__setattr__(self, "pivot", _vector(pivot, 3, "pivot (mm)"))

    # ----------------------------------------------------------- constructors
    @classmethod
    def identity(cls, pivot=(0.0, 0.0, 0.0)) -> RigidMotion:
        """No motion; ``pivot`` (3,) mm."""
        return cls(pivot=pivot)

    @classmethod
    def from_rotation_vector(cls, rotvec_deg, translation=(0.0, 0.0, 0.0), pivot=(0.0, 0.0, 0.0)) -> RigidMotion:
        """From ``rotvec_deg`` (3,) = unit axis times angle in degrees; translation, pivot (3,) mm."""
        rotvec = np.deg2rad(_vector(rotvec_deg, 3, "rotation_vector_deg"))
        return cls(_quaternion_from_rotvec(rotvec), translation, pivot)

    @classmethod
    def from_euler_deg(cls, angles_deg, translation=(0.0, 0.0, 0.0), pivot=(0.0, 0.0, 0.0)) -> RigidMotion:
        """From ``angles_deg`` (3,) about the fixed x, y, z axes applied in that order
        (``R = Rz Ry Rx``); translation, pivot (3,) mm."""
        from scipy.spatial.transform import Rotation

        x, y, z, w = Rotation.from_euler("xyz", _vector(angles_deg, 3, "euler_deg"), degrees=True).as_quat()
        return cls((w, x, y, z), translation, pivot)

    @classmethod
    def from_matrix(cls, matrix, translation=(0.0, 0.0, 0.0), pivot=(0.0, 0.0, 0.0)) -> RigidMotion:
        """From a proper rotation ``matrix`` (3, 3); translation, pivot (3,) mm."""
        from scipy.spatial.transform import Rotation

        m = np.asarray(matrix, dtype=float)
        if m.shape != (3, 3) or not np.all(np.isfinite(m)):
            raise PlanError(f"rotation matrix has shape {m.shape} (or holds NaN); expected a finite (3, 3) array")
        err, det = float(np.abs(m.T @ m - np.eye(3)).max()), float(np.linalg.det(m))
        if err > 1e-6 or det <= 0:
            raise PlanError(
                f"matrix is not a proper rotation (|M^T M - I| = {err:.3g}, det = {det:.6g}); "
                "expected an orthogonal matrix with det = +1"
            )
        x, y, z, w = Rotation.from_matrix(m).as_quat()
        return cls((w, x, y, z), translation, pivot)

    # ------------------------------------------------------------- properties
    @property
    def matrix(self) -> np.ndarray:
        """Rotation matrix, (3, 3)."""
        w, x, y, z = self.rotation
        return np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )

    @property
    def angle_deg(self) -> float:
        """Rotation angle in degrees, in [0, 180]."""
        return math.degrees(2.0 * math.atan2(float(np.linalg.norm(self.rotation[1:])), abs(self.rotation[0])))

    @property
    def rotation_vector_deg(self) -> np.ndarray:
        """Unit axis times angle in degrees, (3,)."""
        v = self.rotation[1:]
        s = float(np.linalg.norm(v))
        return np.zeros(3) if s == 0.0 else v / s * self.angle_deg

    @property
    def translation_mm(self) -> float:
        """Distance travelled by the pivot, mm."""
        return float(np.linalg.norm(self.translation))

    @property
    def is_identity(self) -> bool:
        """True when neither rotating nor translating."""
        return not np.any(self.rotation[1:]) and not np.any(self.translation)

    # ------------------------------------------------------------- operations
    def apply(self, points) -> np.ndarray:
        """Moved points: ``points`` (n, 3) mm -> (n, 3) mm (a (3,) point also works)."""
        p = np.asarray(points, dtype=float)
        return (p - self.pivot) @ self.matrix.T + self.pivot + self.translation

    def displacement(self, points) -> np.ndarray:
        """Displacement ``apply(points) - points``: (n, 3) mm -> (n, 3) mm."""
        return self.apply(points) - np.asarray(points, dtype=float)

    def scaled(self, factor: float) -> RigidMotion:
        """The motion with rotation angle and translation multiplied by ``factor`` (same
        axis and pivot); ``factor`` in [0, 1] is the quaternion slerp from the identity."""
        factor = float(factor)
        if not math.isfinite(factor):
            raise PlanError(f"factor = {factor!r}; expected a finite number")
        if factor == 1.0:
            return self
        w, v = self.rotation[0], self.rotation[1:]
        s = float(np.linalg.norm(v))
        if s == 0.0:
            return RigidMotion(self.rotation, factor * self.translation, self.pivot)
        half = math.atan2(s, w)  # half the angle, in [0, pi/2] since w >= 0: the short arc
        q = np.concatenate([[math.cos(factor * half)], math.sin(factor * half) / s * v])
        return RigidMotion(q, factor * self.translation, self.pivot)

    def interpolated(self, fraction: float) -> RigidMotion:
        """The motion ``fraction`` in [0, 1] of the way from the identity: rotation by
        quaternion slerp (short arc), translation linear, same pivot."""
        if not 0.0 <= fraction <= 1.0:
            raise PlanError(f"fraction = {fraction!r}; expected a number in [0, 1]")
        return self.scaled(fraction)

    def inverted(self) -> RigidMotion:
        """The inverse motion (expressed about the moved pivot ``pivot + translation``)."""
        conj = self.rotation * np.array([1.0, -1.0, -1.0, -1.0])
        return RigidMotion(conj, -self.translation, self.pivot + self.translation)

    def after(self, first: RigidMotion) -> RigidMotion:
        """The motion ``first`` followed by ``self``, expressed about ``first.pivot``."""
        t = (
            self.matrix @ (first.pivot + first.translation - self.pivot)
            + self.pivot
            + self.translation
            - first.pivot
        )
        return RigidMotion(_hamilton(self.rotation, first.rotation), t, first.pivot)

    def to_dict(self) -> dict[str, list[float]]:
        """Plain floats: ``rotation_quaternion`` (w, x, y, z), the readable
        ``rotation_vector_deg``, ``translation_mm`` and ``pivot_mm``."""
        return {
            "translation_mm": [float(v) for v in self.translation],
            "rotation_quaternion": [float(v) for v in self.rotation],
            "rotation_vector_deg": [float(v) for v in self.rotation_vector_deg],
            "pivot_mm": [float(v) for v in self.pivot],
        }

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], pivot=None) -> RigidMotion:
        """From the keys of :meth:`to_dict`; give at most one of ``rotation_quaternion``,
        ``rotation_vector_deg``, ``euler_deg`` — or the quaternion with the rotation
        vector, which must then agree (to 1e-6 degrees). Missing ``translation_mm``:
        zero; missing rotation: none; missing ``pivot_mm``: ``pivot`` (3,) mm if given,
        else required unless the motion does not rotate."""
        unknown = sorted(set(d) - set(_MOTION_KEYS))
        if unknown:
            raise PlanError(f"unknown keys {unknown}; expected some of {list(_MOTION_KEYS)}"
                            f"{_did_you_mean(unknown[0], _MOTION_KEYS)}")
        given = [k for k in _ROTATION_KEYS if k in d]
        if len(given) > 1 and set(given) != {"rotation_quaternion", "rotation_vector_deg"}:
            raise PlanError(f"rotation given as {given}; give one of {list(_ROTATION_KEYS)}")
        translation = _vector(d.get("translation_mm", (0.0, 0.0, 0.0)), 3, "translation_mm")
        if "rotation_quaternion" in d:
            motion = cls(_vector(d["rotation_quaternion"], 4, "rotation_quaternion"), translation)
            if "rotation_vector_deg" in d:
                other = cls.from_rotation_vector(d["rotation_vector_deg"])
                gap = other.inverted().after(motion).angle_deg
                if gap > 1e-6:
                    raise PlanError(
                        f"rotation_quaternion {motion.rotation.tolist()} and rotation_vector_deg "
                        f"{list(d['rotation_vector_deg'])} differ by {gap:.3g} degrees; give only one"
                    )
        elif "rotation_vector_deg" in d:
            motion = cls.from_rotation_vector(d["rotation_vector_deg"], translation)
        elif "euler_deg" in d:
            motion = cls.from_euler_deg(d["euler_deg"], translation)
        else:
            motion = cls(translation=translation)
        if "pivot_mm" in d:
            pivot = _vector(d["pivot_mm"], 3, "pivot_mm")
        elif pivot is None:
            if motion.angle_deg > 0:
                raise PlanError(
                    "pivot_mm is missing and the segment rotates; give pivot_mm = [x, y, z] (mm) "
                    "or read the plan with a phantom, whose segment pivots fill it in"
                )
            pivot = (0.0, 0.0, 0.0)
        return cls(motion.rotation, motion.translation, pivot)


def _rotation_about(centre: np.ndarray, points: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Proper rotation R (3, 3) minimising ``sum |R (p - c) - (q - c)|^2`` (Kabsch, no translation)."""
    a, b = points - centre, targets - centre
    s = np.linalg.svd(a, compute_uv=False)
    if s.size < 2 or s[1] <= 1e-9 * s[0]:
        raise PlanError(
            f"the {points.shape[0]} reference points are collinear with the centre {centre.tolist()}; "
            "the rotation about it is undetermined — give points spanning a plane"
        )
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T


def _following(distal: RigidMotion, condyle, points) -> RigidMotion:
    """Rotation about ``condyle`` (3,) mm that best follows ``distal`` at ``points`` (n, 3) mm."""
    c = _vector(condyle, 3, "condyle (mm)")
    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 2 or not np.all(np.isfinite(p)):
        raise PlanError(f"reference points have shape {p.shape} (or hold NaN); expected finite (n, 3), n >= 2")
    return RigidMotion.from_matrix(_rotation_about(c, p, distal.apply(p)), pivot=c)


def proximal_reference_points(phantom: FacePhantom | FaceAnatomy,
                              fraction: float = 0.25) -> tuple[np.ndarray, np.ndarray]:
    """Reference points of the proximal segments for following the distal one.

    The ``fraction`` of each proximal surface's vertices nearest to the distal
    segment's surface (at least 3; ties within 1e-6 mm all kept, so a symmetric
    phantom gives mirror-image sets): the region of the sagittal split, where the two
    segments are plated together. Returns ``(points_left, points_right)``, each (k, 3) mm.
    """
    from scipy.spatial import cKDTree

    if not 0.0 < fraction <= 1.0:
        raise PlanError(f"fraction = {fraction!r}; expected a number in (0, 1]")
    distal = cKDTree(phantom.segments["distal"].surface.points)
    out = []
    for name in ("proximal_left", "proximal_right"):
        pts = phantom.segments[name].surface.points
        dist = distal.query(pts)[0]
        k = min(pts.shape[0], max(3, round(fraction * pts.shape[0])))
        out.append(pts[dist <= np.partition(dist, k - 1)[k - 1] + 1e-6])
    return out[0], out[1]


def _check_names(names) -> None:
    unknown = sorted(set(names) - set(SEGMENTS))
    if unknown:
        raise PlanError(f"unknown segments {unknown}; the known segments are {list(SEGMENTS)}"
                        f" (and the key 'force'){_did_you_mean(unknown[0], (*SEGMENTS, 'force'))}")


@dataclass(frozen=True, eq=False)
class SurgicalPlan:
    """Rigid motions of the bony segments, validated at construction.

    Attributes
    ----------
    motions : mapping segment -> RigidMotion for every name in :data:`SEGMENTS`
        (segments not given are the identity); read-only
    force : bool — accept movements beyond twice the physiological range (with a
        :class:`PlanRangeWarning` instead of a :class:`PlanError`)
    """

    motions: Mapping[str, RigidMotion]
    force: bool = False

    def __post_init__(self):
        if not isinstance(self.motions, Mapping):
            raise TypeError(f"motions is a {type(self.motions).__name__}; expected a mapping segment -> RigidMotion")
        _check_names(self.motions)
        for name, m in self.motions.items():
            if not isinstance(m, RigidMotion):
                raise TypeError(f"segment {name!r} has a {type(m).__name__}; expected a RigidMotion")
        full = {name: self.motions.get(name, RigidMotion.identity()) for name in SEGMENTS}
        object.__setattr__(self, "motions", MappingProxyType(full))
        object.__setattr__(self, "force", bool(self.force))
        self._validate(self.force, stacklevel=4)  # warn at the caller of SurgicalPlan(...)

    def validate(self, force: bool | None = None) -> None:
        """Check every movement against :data:`PHYSIOLOGICAL_RANGES` (done at construction).

        Beyond the range: :class:`PlanRangeWarning`. Beyond twice the range:
        :class:`PlanError`, or a warning when ``force`` (default: the plan's own) is true.
        """
        self._validate(self.force if force is None else force, stacklevel=3)

    def _validate(self, force: bool, stacklevel: int) -> None:
        for name, m in self.motions.items():
            max_mm, max_deg = PHYSIOLOGICAL_RANGES[name].translation_mm[1], PHYSIOLOGICAL_RANGES[name].rotation_deg[1]
            checks = (("translation", m.translation_mm, max_mm, "mm"), ("rotation", m.angle_deg, max_deg, "degrees"))
            for what, value, limit, unit in checks:
                if value <= limit:
                    continue
                msg = (
                    f"segment {name!r}: {what} {value:.3g} {unit} is beyond the physiological "
                    f"range 0-{limit} {unit} (the lip-sliding paper)"
                )
                if value > 2 * limit:
                    if not force:
                        raise PlanError(f"{msg} by more than twice; build the plan with force=True "
                                        "(command line: --force) to accept it")
                    msg += ", more than twice; accepted because force=True"
                warnings.warn(msg, PlanRangeWarning, stacklevel=stacklevel)

    # ------------------------------------------------------------ constructors
    @classmethod
    def for_phantom(
        cls,
        phantom: FacePhantom | FaceAnatomy,
        *,
        lefort: RigidMotion | Mapping[str, Any] | None = None,
        distal: RigidMotion | Mapping[str, Any] | None = None,
        proximal_left: RigidMotion | Mapping[str, Any] | None = None,
        proximal_right: RigidMotion | Mapping[str, Any] | None = None,
        force: bool = False,
    ) -> SurgicalPlan:
        """A plan on ``phantom``: each segment is a RigidMotion (kept as is) or a mapping
        in the file format whose missing ``pivot_mm`` is the phantom segment's pivot.
        Proximal segments not given follow the distal one (about the phantom's condyles,
        at :func:`proximal_reference_points`). ``phantom`` may be a meshed face's
        :class:`~toolkit.static.anatomy.FaceAnatomy`; one without proximal segments gets no
        proximal motions."""
        given = {"lefort": lefort, "distal": distal, "proximal_left": proximal_left, "proximal_right": proximal_right}
        motions = {}
        for name, spec in given.items():
            if isinstance(spec, Mapping):
                try:
                    spec = RigidMotion.from_dict(spec, pivot=phantom.segments[name].pivot)
                except ValueError as exc:
                    raise PlanError(f"segment {name!r}: {exc}") from exc
            if spec is not None:
                motions[name] = spec
        if not {"proximal_left", "proximal_right"} <= set(phantom.segments):
            return cls(motions, force=force)
        d = motions.get("distal", RigidMotion.identity())
        reference = proximal_reference_points(phantom)
        for side, name in enumerate(("proximal_left", "proximal_right")):
            if name not in motions:
                motions[name] = _following(d, phantom.condyles[side], reference[side])
        return cls(motions, force=force)

    def with_proximal_following(self, condyles, points_left, points_right) -> SurgicalPlan:
        """A copy whose proximal segments rotate about their condyle to follow the distal one.

        Parameters
        ----------
        condyles : (2, 3) float, mm — left (x > 0) then right condyle centre (the pivots)
        points_left, points_right : (n, 3) float, mm — reference points of each proximal
            segment (e.g. its bone-surface vertices), spanning a plane with the condyle

        Each side gets the proper rotation R about its condyle c minimising
        ``sum |R (p - c) - (D(p) - c)|^2`` over its points (D the distal motion), no translation.
        """
        c = np.asarray(condyles, dtype=float)
        if c.shape != (2, 3):
            raise PlanError(f"condyles has shape {c.shape}, expected (2, 3): left then right, mm")
        d = self.motions["distal"]
        motions = dict(self.motions)
        motions["proximal_left"] = _following(d, c[0], points_left)
        motions["proximal_right"] = _following(d, c[1], points_right)
        return SurgicalPlan(motions, force=self.force)

    def motion(self, name: str) -> RigidMotion:
        """The motion of segment ``name``; a bone no plan moves (the phantoms' ``skull``,
        on which the degloved tissue above the Le Fort I cut slides) stays: the identity."""
        return self.motions.get(name) or RigidMotion.identity()

    # -------------------------------------------------------------- transforms
    def scaled(self, factor: float) -> SurgicalPlan:
        """Every segment's rotation angle and translation times ``factor`` (pivots kept)."""
        return SurgicalPlan({k: m.scaled(factor) for k, m in self.motions.items()}, force=self.force)

    def interpolated(self, fraction: float) -> SurgicalPlan:
        """The plan ``fraction`` in [0, 1] of the way from pre-op (slerp + linear)."""
        if not 0.0 <= fraction <= 1.0:
            raise PlanError(f"fraction = {fraction!r}; expected a number in [0, 1]")
        return self.scaled(fraction)

    def increments(self, n: int = 3) -> list[SurgicalPlan]:
        """The cumulative plans (pre-op -> k-th position) at fractions k/n, k = 1..n;
        the last is this plan. The lip-sliding paper uses n = 3."""
        if int(n) != n or n < 1:
            raise PlanError(f"n = {n!r} increments; expected an integer >= 1")
        n = int(n)
        return [self.interpolated(k / n) for k in range(1, n + 1)]

    # ---------------------------------------------------------------- dict/I-O
    def to_dict(self) -> dict[str, Any]:
        """``{"force": bool, segment: RigidMotion.to_dict(), ...}`` of plain Python values."""
        return {"force": self.force, **{k: m.to_dict() for k, m in self.motions.items()}}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any], phantom: FacePhantom | FaceAnatomy | None = None) -> SurgicalPlan:
        """Inverse of :meth:`to_dict` (optional ``force``); with a ``phantom``, missing
        pivots come from its segments and missing proximal segments follow the distal one."""
        force = d.get("force", False)
        if not isinstance(force, bool):
            raise PlanError(f"force = {force!r}; expected true or false")
        segments = {k: v for k, v in d.items() if k != "force"}
        _check_names(segments)
        for name, spec in segments.items():
            if not isinstance(spec, Mapping):
                raise PlanError(
                    f"segment {name!r} is a {type(spec).__name__}; expected a table of {list(_MOTION_KEYS)}"
                )
        if phantom is not None:
            return cls.for_phantom(phantom, force=force, **segments)
        motions = {}
        for name, spec in segments.items():
            try:
                motions[name] = RigidMotion.from_dict(spec)
            except ValueError as exc:
                raise PlanError(f"segment {name!r}: {exc}") from exc
        return cls(motions, force=force)

    @classmethod
    def read(cls, path, phantom: FacePhantom | FaceAnatomy | None = None, *, force: bool = False) -> SurgicalPlan:
        """Read a ``.toml`` or ``.json`` plan (see the module docstring for the keys); ``force``
        accepts movements beyond twice the physiological range whatever the file says."""
        path = Path(path)
        fmt = _format(path)
        if not path.is_file():
            raise FileNotFoundError(f"plan file {str(path)!r} does not exist; expected a .toml or .json plan "
                                    "(command line: --plan FILE)")
        d = _load(path, fmt)
        if force and isinstance(d, dict):
            d = {**d, "force": True}
        try:
            return cls.from_dict(d, phantom)
        except ValueError as exc:
            raise PlanError(f"{path}: {exc}") from exc

    def write(self, path) -> None:
        """Write ``.toml`` or ``.json`` (atomically: temporary file, then rename)."""
        path = Path(path)
        fmt = _format(path)
        text = _toml(self.to_dict()) if fmt == ".toml" else json.dumps(self.to_dict(), indent=2) + "\n"
        with atomic_path(path) as tmp:
            tmp.write_text(text, encoding="utf-8")

    def summary(self) -> pd.DataFrame:
        """One row per segment: ``segment``, ``translation_mm``, ``rotation_deg``."""
        import pandas as pd

        rows = [(k, m.translation_mm, m.angle_deg) for k, m in self.motions.items()]
        return pd.DataFrame(rows, columns=["segment", "translation_mm", "rotation_deg"])


def _load(path: Path, fmt: str) -> dict[str, Any]:
    """The plan file's top-level table; syntax errors name the file and the line."""

    text = read_text(path, PlanError, f"a {fmt[1:].upper()} plan")
    try:
        d = tomllib.loads(text) if fmt == ".toml" else json.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise PlanError(f"{path}: not valid TOML: {exc}") from None
    except json.JSONDecodeError as exc:
        raise PlanError(f"{path}, line {exc.lineno}, column {exc.colno}: not valid JSON: {exc.msg}") from None
    if not isinstance(d, dict):
        raise PlanError(f"{path} holds a JSON {type(d).__name__}; expected an object of segment tables")
    if not d:
        raise PlanError(f"{path} is empty; expected one table per moved segment, of {list(SEGMENTS)}"
                        f" (see the packaged default_plan.toml)")
    return d


def _did_you_mean(name: str, known) -> str:
    close = difflib.get_close_matches(str(name), list(known), n=1)
    return f"; did you mean {close[0]!r}?" if close else ""


def _format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix not in PLAN_FORMATS:
        raise PlanError(f"unknown plan format {path.suffix!r} of {str(path)!r}; expected one of {list(PLAN_FORMATS)}")
    return suffix


def _toml(d: Mapping[str, Any]) -> str:
    """The dict of :meth:`SurgicalPlan.to_dict` as TOML (floats by repr: exact)."""
    lines = [
        "# Surgical plan (toolkit.static.plan): x' = R (x - pivot) + pivot + translation, mm.",
        "# Axes: x patient's left, y anterior, z superior. rotation_quaternion = [w, x, y, z];",
        "# rotation_vector_deg (axis * angle) must agree with it when both are given.",
        f"force = {'true' if d['force'] else 'false'}",
    ]
    for name in SEGMENTS:
        lines += ["", f"[{name}]"]
        lines += [f"{k} = [{', '.join(repr(float(v)) for v in vals)}]" for k, vals in d[name].items()]
    return "\n".join(lines) + "\n"


def default_plan(phantom: FacePhantom | FaceAnatomy, force: bool = False) -> SurgicalPlan:
    """The packaged typical bimaxillary plan on ``phantom``.

    Le Fort I: advance 4 mm (+y), impaction 2 mm (-z), 3 degrees about +x; distal
    mandible: setback 6 mm (-y), 5 degrees about +x. Pivots are the phantom segments'
    (Le Fort: attachment centroid, distal: midpoint of the condyles) and the proximal
    segments follow the distal one about their condyles.
    """
    ref = resources.files("toolkit.static").joinpath("data", "default_plan.toml")
    d = tomllib.loads(ref.read_text(encoding="utf-8"))
    if force:
        d["force"] = True
    return SurgicalPlan.from_dict(d, phantom)


def _directions(rng: np.random.Generator, n: int, mode: str) -> np.ndarray:
    """``n`` random unit vectors (n, 3): uniform on the y-z circle (``sagittal``) or the sphere."""
    if mode == "sagittal":
        phi = rng.uniform(0.0, 2.0 * math.pi, n)
        return np.stack([np.zeros(n), np.cos(phi), np.sin(phi)], axis=1)
    v = rng.normal(size=(n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


#: mm, largest craniocaudal closing of the mandibular onto the maxillary teeth that
#: :func:`sample_plans` accepts: the crown height of an incisor (~10 mm). A plan that closes
#: the jaws further drives the teeth through each other, which no surgery does.
MAX_JAW_CLOSING_MM = 10.0


def dental_arch(phantom: FacePhantom | FaceAnatomy) -> np.ndarray:
    """Bone-side points of the occlusal plane under the Le Fort I segment, ``(k, 3)`` mm:
    where the upper and lower teeth meet (``z = 0`` in the phantoms' axes; a meshed face's
    :attr:`FaceAnatomy.arch <toolkit.static.anatomy.FaceAnatomy.arch>`)."""
    if hasattr(phantom, "arch"):
        return phantom.arch
    mesh = phantom.mesh
    bone = mesh.node_sets["bone"]
    pts = mesh.points[bone]
    maxilla = mesh.points[mesh.node_sets["maxilla"]]
    width = np.abs(maxilla[:, 0]).max()
    return np.unique(pts[(np.abs(pts[:, 2]) < 1e-6) & (np.abs(pts[:, 0]) <= width)], axis=0)


def jaw_closing(plan: SurgicalPlan, arch: np.ndarray) -> float:
    """Largest craniocaudal closing of the jaws at the teeth, mm (0 when they only separate).

    ``max over the arch points p of z(distal(p)) - z(lefort(p))``: how far the mandibular
    teeth would pass through the maxillary ones. ``arch`` (k, 3) mm, e.g. :func:`dental_arch`.
    """
    arch = np.asarray(arch, dtype=float).reshape(-1, 3)
    dz = plan.motions["distal"].apply(arch)[:, 2] - plan.motions["lefort"].apply(arch)[:, 2]
    return float(max(0.0, dz.max(initial=0.0)))


#: the segments :func:`sample_plans` moves (the proximal ones follow the distal one)
SAMPLED_SEGMENTS = ("lefort", "distal")


def sampled_parameters(plan: SurgicalPlan, arch: np.ndarray | None = None) -> dict[str, float]:
    """What :func:`sample_plans` draws, read back from ``plan``.

    Per moved segment (:data:`SAMPLED_SEGMENTS`): ``<segment>.translation_mm`` the length of
    the pivot's translation, ``<segment>.rotation_deg`` the rotation angle,
    ``<segment>.lateral_translation_mm`` the translation's ``|x|`` and
    ``<segment>.off_axis_rotation_deg`` the rotation about axes other than x (both zero in a
    sagittal plan); with ``arch`` ``(k, 3)`` mm (:func:`dental_arch`), ``jaw_closing_mm``
    (:func:`jaw_closing`). Units mm and degrees.
    """
    values = {}
    for name in SAMPLED_SEGMENTS:
        m = plan.motion(name)
        t, r = np.asarray(m.translation, float), np.asarray(m.rotation_vector_deg, float)
        values.update({f"{name}.translation_mm": float(np.linalg.norm(t)),
                       f"{name}.rotation_deg": float(np.linalg.norm(r)),
                       f"{name}.lateral_translation_mm": float(abs(t[0])),
                       f"{name}.off_axis_rotation_deg": float(np.linalg.norm(r[1:]))})
    if arch is not None:
        values["jaw_closing_mm"] = jaw_closing(plan, arch)
    return values


def sampling_hull(mode: str = "sagittal", ranges: Mapping[str, MotionRange] = PHYSIOLOGICAL_RANGES,
                  max_jaw_closing_mm: float | None = MAX_JAW_CLOSING_MM) -> dict[str, list[float]]:
    """What :func:`sample_plans` spans with these settings: :func:`sampled_parameters`'s name ->
    ``[min, max]`` (mm, degrees) bounding, segment by segment, the convex hull of the motions it
    draws.

    It draws translation lengths and rotation angles uniform in ``ranges``, in every direction of
    the plane (``sagittal``: no lateral translation, rotation about x only) or of the space
    (``full``), so a motion is within the hull when its length and angle are at most the top of
    the range, wherever they are below the bottom: a shorter motion (an unrotated distal segment,
    say) lies between drawn ones of opposite directions. ``jaw_closing_mm`` is bounded when
    ``max_jaw_closing_mm`` is set (draws beyond it are rejected)."""
    if mode not in SAMPLING_MODES:
        raise PlanError(f"unknown sampling mode {mode!r}; expected one of {SAMPLING_MODES}")
    hull, sagittal = {}, mode == "sagittal"
    for name in SAMPLED_SEGMENTS:
        top_mm, top_deg = float(ranges[name].translation_mm[1]), float(ranges[name].rotation_deg[1])
        hull.update({f"{name}.translation_mm": [0.0, top_mm], f"{name}.rotation_deg": [0.0, top_deg],
                     f"{name}.lateral_translation_mm": [0.0, 0.0 if sagittal else top_mm],
                     f"{name}.off_axis_rotation_deg": [0.0, 0.0 if sagittal else top_deg]})
    if max_jaw_closing_mm is not None:
        hull["jaw_closing_mm"] = [0.0, float(max_jaw_closing_mm)]
    return hull


def sample_plans(n: int, seed: int | np.random.Generator, mode: str = "sagittal",
                 ranges: Mapping[str, MotionRange] = PHYSIOLOGICAL_RANGES, *,
                 phantom: FacePhantom | FaceAnatomy,
                 max_jaw_closing_mm: float | None = MAX_JAW_CLOSING_MM) -> list[SurgicalPlan]:
    """Random bimaxillary plans within ``ranges`` (the lip-sliding paper's physiological ranges by default).

    Both the Le Fort I and the distal mandibular segment move in every plan: the
    translation magnitude of the pivot (mm) and the rotation angle (degrees) are uniform
    in the segment's :class:`MotionRange`; their directions follow ``mode`` (see
    :data:`SAMPLING_MODES`: ``sagittal`` translations in the y-z plane and rotations about
    +-x, ``full`` uniform on the sphere). Pivots are the phantom's segment pivots and the
    proximal segments follow the distal one about their condyles.

    The two movements are drawn independently, so some pairs would drive the mandibular
    teeth through the maxillary ones (by more than a crown's height at the edges of the
    ranges). A plan whose :func:`jaw_closing` exceeds ``max_jaw_closing_mm`` is drawn again
    (rejection); ``None`` keeps every draw.

    Parameters
    ----------
    n : number of plans
    seed : int or numpy Generator (the only source of randomness)
    mode : ``sagittal`` or ``full``
    ranges : segment -> MotionRange for ``lefort`` and ``distal``
    phantom : FacePhantom, or a meshed face's FaceAnatomy (:func:`toolkit.static.anatomy.face_anatomy`),
        whose pivots, condyles and dental arch the plans use
    max_jaw_closing_mm : mm, or None (see above; default :data:`MAX_JAW_CLOSING_MM`)

    Returns
    -------
    list of n SurgicalPlan; plan ``i`` depends only on ``seed`` and ``i`` (drawing more plans
    with the same seed extends the list)
    """
    if int(n) != n or n < 0:
        raise PlanError(f"n = {n!r} plans; expected an integer >= 0")
    if mode not in SAMPLING_MODES:
        raise PlanError(f"unknown sampling mode {mode!r}; expected one of {SAMPLING_MODES}")
    missing = [k for k in ("lefort", "distal") if k not in ranges]
    if missing:
        raise PlanError(f"ranges lacks {missing}; expected a MotionRange for 'lefort' and 'distal'")
    if max_jaw_closing_mm is not None and not (np.isfinite(max_jaw_closing_mm) and max_jaw_closing_mm >= 0):
        raise PlanError(f"max_jaw_closing_mm = {max_jaw_closing_mm!r}; expected a number >= 0 mm or None")
    arch = dental_arch(phantom) if max_jaw_closing_mm is not None else None
    # one independent stream per plan, spawned from the seed: plan i is the same whatever n is
    streams = np.random.default_rng(seed).spawn(int(n))
    plans = []
    for r in streams:
        for _ in range(1000):
            motions = {}
            for name in SAMPLED_SEGMENTS:
                rg = ranges[name]
                t = r.uniform(*rg.translation_mm) * _directions(r, 1, mode)[0]
                axis = np.array([r.choice([-1.0, 1.0]), 0.0, 0.0]) if mode == "sagittal" \
                    else _directions(r, 1, mode)[0]
                angle = r.uniform(*rg.rotation_deg)
                motions[name] = RigidMotion.from_rotation_vector(angle * axis, t, phantom.segments[name].pivot)
            plan = SurgicalPlan.for_phantom(phantom, lefort=motions["lefort"], distal=motions["distal"])
            if arch is None or max_jaw_closing_mm is None or jaw_closing(plan, arch) <= max_jaw_closing_mm:
                break
        else:
            raise PlanError(f"no plan in 1000 draws closes the jaws by at most {max_jaw_closing_mm} mm; "
                             f"the ranges force larger closings")
        plans.append(plan)
    return plans
