"""Anatomical axes: the toolkit's, those of other tools, and the check that a face is in the toolkit's.

The toolkit works in mm with **x toward the patient's left, y anterior, z superior**. Files from
other tools come in other axes; :data:`AXES` names the ones the toolkit converts on reading:

=========  ===========  ==========  =========  ==============  =================================
axes       x            y           z          to the toolkit  written by
=========  ===========  ==========  =========  ==============  =================================
toolkit    left         anterior    superior   as is           the toolkit, its phantoms
LPS        left         posterior   superior   y negated       DICOM, ITK-SNAP
RAS        right        anterior    superior   x negated       3D Slicer models
=========  ===========  ==========  =========  ==============  =================================

Both conversions are mirrors: a mirrored cell is inside out. :func:`to_toolkit` converts points
only; :func:`mesh_to_toolkit` also reorders each cell's nodes (its reference element reflected),
so that volumes stay positive and surface triangles keep their outward winding.

:func:`check_anatomical_axes` reads the axes off the anatomy and refuses a face that is not in the
toolkit's, with the conversion that fits. Each criterion is a fact of every human face that a
mirror, an upside-down or a swapped axis breaks:

- **the face's front is narrow and central**: the skin within :data:`FRONT_DEPTH_MM` of its most
  anterior point (the nose tip, or the lips or chin) spans at most :data:`FRONT_SPAN` of the face's
  width and is centred within :data:`FRONT_OFFSET` of the width on its middle. Behind a face, and
  above or below it, a face model ends in a cut or a curve across its whole width;
- **the skin covers the bones in front**: the most anterior skin point lies in front of the most
  anterior bone point (the nose, lips and chin stand 10-30 mm in front of the skeleton);
- **the maxilla lies above the mandible**: the Le Fort I segment's centre above the distal
  mandible's;
- **the mandible's body lies in front of its rami**: the distal segment's centre in front of the
  proximal segments';
- **the left ramus lies on the left**: ``proximal_left`` at larger x than ``proximal_right``;
- without named jaws, **the face narrows toward the chin and turns back beneath it**: refused only
  when both fail, the lowest fifth of the skin wider than its highest fifth and the lowest tenth
  reaching farther forward than the highest tenth.

A face is left-right symmetric: without the proximal segments' sides a left-right mirror (RAS read
as the toolkit's axes) cannot be told from the anatomy, so RAS files must be declared.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import dataclass, replace

import numpy as np

from toolkit.common.errors import ToolkitError
from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.mesh import Mesh

__all__ = ["AXES", "AxesError", "axes_matrix", "to_toolkit", "mesh_to_toolkit", "check_anatomical_axes",
           "check_mesh_axes", "skin_points", "SEGMENT_SETS", "FRONT_DEPTH_MM", "FRONT_SPAN", "FRONT_OFFSET"]

#: the axes a file may be in (``axes=``, command line ``--axes``)
AXES = ("toolkit", "LPS", "RAS")
#: per axes, the sign each coordinate takes in the toolkit's axes
_SIGNS = {"toolkit": (1.0, 1.0, 1.0), "LPS": (1.0, -1.0, 1.0), "RAS": (-1.0, 1.0, 1.0)}
_DESCRIBED = {"toolkit": "x left, y anterior, z superior", "LPS": "x left, y posterior, z superior: DICOM, ITK-SNAP",
              "RAS": "x right, y anterior, z superior: 3D Slicer"}

#: mm, depth behind the most anterior skin point that makes the face's front
FRONT_DEPTH_MM = 5.0
#: largest width of the face's front, as a fraction of the face's width
FRONT_SPAN = 0.6
#: largest distance of the front's centre from the face's middle, as a fraction of its width
FRONT_OFFSET = 0.2

#: node sets of a face mesh that lie on each bony segment (the phantom's and ``toolkit mesh``'s)
SEGMENT_SETS = {"lefort": ("maxilla", "mucosa_lefort"), "distal": ("mandible", "mucosa_distal"),
                "proximal_left": ("mucosa_proximal_left",), "proximal_right": ("mucosa_proximal_right",),
                "skull": ("mucosa_skull",)}


class AxesError(ToolkitError, ValueError):
    """A face that is not in the toolkit's axes (x left, y anterior, z superior), or an unknown
    ``axes`` name."""


def axes_matrix(axes: str) -> np.ndarray:
    """The ``(3, 3)`` matrix ``M`` taking points in ``axes`` to the toolkit's:
    ``toolkit = points @ M.T``. Raises :class:`AxesError` for a name not in :data:`AXES`."""
    if axes not in _SIGNS:
        raise AxesError(f"axes = {axes!r}; expected one of {', '.join(AXES)} (command line: --axes)")
    return np.diag(_SIGNS[axes])


def to_toolkit(points, axes: str) -> np.ndarray:
    """Points in ``axes`` (a name of :data:`AXES`) in the toolkit's axes.

    points : (n, 3) float, mm (or one point (3,))
    Returns a new array of the same shape, mm. Converts points only: the cells of a mirrored mesh
    are inside out (:func:`mesh_to_toolkit` reorders them; ``toolkit mesh`` re-orients the
    surfaces it reads).
    """
    m = axes_matrix(axes)
    p = np.asarray(points, dtype=float)
    if p.shape[-1:] != (3,):
        raise AxesError(f"points have shape {p.shape}; expected (n, 3) or (3,) mm")
    return p @ m.T


def mesh_to_toolkit(mesh: Mesh, axes: str) -> Mesh:
    """``mesh`` in the toolkit's axes: its points converted from ``axes`` and, for a mirror, each
    cell's nodes reordered (reflected on its reference element), so that volumes stay positive
    and surfaces keep their winding. Point and cell fields of three components per entry
    (vectors: ``fibre_direction``, ``displacement``) are converted too; sets are unchanged.
    Returns ``mesh`` itself for ``axes="toolkit"``."""
    m = axes_matrix(axes)
    if axes == "toolkit":
        return mesh
    cells = dict(mesh.cells)
    if np.linalg.det(m) < 0:
        cells = {t: c[:, _mirror_order(t)] for t, c in cells.items()}

    def fields(data):
        return {k: (v @ m.T if v.ndim == 2 and v.shape[1] == 3 else v) for k, v in data.items()}

    return replace(mesh, points=mesh.points @ m.T, cells=cells, point_data=fields(mesh.point_data),
                   cell_data=fields(mesh.cell_data))


def _mirror_order(cell_type: str) -> np.ndarray:
    """The node order of a cell of ``cell_type`` that undoes a mirror: the reference nodes with
    their first two reference coordinates swapped (a reflection of the reference element)."""

    nodes = REFERENCE_ELEMENTS[cell_type].nodes
    swapped = nodes.copy()
    swapped[:, [0, 1]] = nodes[:, [1, 0]]
    return np.array([int(np.flatnonzero(np.all(np.isclose(nodes, s), axis=1))[0]) for s in swapped])


@dataclass(frozen=True)
class _Finding:
    """One criterion: whether it holds, what was found and what a face in the toolkit's axes has."""

    holds: bool
    found: str
    expected: str


def _front(skin: np.ndarray) -> _Finding | None:
    lo, hi = np.percentile(skin[:, 0], [1.0, 99.0])
    width = hi - lo
    if width <= 0:
        return None
    tip = skin[:, 1].max()
    front = skin[skin[:, 1] >= tip - FRONT_DEPTH_MM, 0]
    span, offset = np.ptp(front), abs(0.5 * (front.min() + front.max()) - 0.5 * (lo + hi))
    return _Finding(
        span <= FRONT_SPAN * width and offset <= FRONT_OFFSET * width,
        f"the skin within {FRONT_DEPTH_MM:g} mm of its most anterior point (y = {tip:.1f} mm) spans x = "
        f"{front.min():.1f} to {front.max():.1f} mm, {span / width:.0%} of the face's {width:.0f} mm width, centred "
        f"{offset:.0f} mm from its middle",
        f"a narrow front near the mid-sagittal plane, the nose, lips or chin: at most {FRONT_SPAN:.0%} of the width, "
        f"centred within {FRONT_OFFSET:.0%} of it")


def _covers_bones(skin: np.ndarray, bones: np.ndarray | None) -> _Finding | None:
    if bones is None or not len(bones):
        return None
    tip, bone = skin[:, 1].max(), bones[:, 1].max()
    return _Finding(tip > bone,
                    f"the most anterior skin point is at y = {tip:.1f} mm, behind the bones' most anterior point at "
                    f"y = {bone:.1f} mm",
                    "the skin in front of every bone: the nose, lips and chin cover the facial skeleton")


def _jaws(named: Mapping[str, np.ndarray]) -> _Finding | None:
    if "lefort" not in named or "distal" not in named:
        return None
    upper, lower = named["lefort"][:, 2].mean(), named["distal"][:, 2].mean()
    return _Finding(upper > lower,
                    f"the Le Fort I segment's centre is at z = {upper:.1f} mm, below the distal mandible's at z = "
                    f"{lower:.1f} mm",
                    "the maxilla above the mandible")


def _rami(named: Mapping[str, np.ndarray]) -> _Finding | None:
    rami = [named[k] for k in ("proximal_left", "proximal_right") if k in named]
    if "distal" not in named or not rami:
        return None
    body, ramus = named["distal"][:, 1].mean(), np.mean([r[:, 1].mean() for r in rami])
    return _Finding(body > ramus,
                    f"the distal mandible's centre is at y = {body:.1f} mm, behind the proximal segments' at y = "
                    f"{ramus:.1f} mm",
                    "the body and chin of the mandible in front of its rami")


def _sides(named: Mapping[str, np.ndarray]) -> _Finding | None:
    if "proximal_left" not in named or "proximal_right" not in named:
        return None
    left, right = named["proximal_left"][:, 0].mean(), named["proximal_right"][:, 0].mean()
    return _Finding(left > right,
                    f"proximal_left's centre is at x = {left:.1f} mm, right of proximal_right's at x = {right:.1f} mm",
                    "the left ramus on the patient's left, at larger x, unless the two files are swapped")


def _chin(skin: np.ndarray) -> _Finding | None:
    z = skin[:, 2]
    lo, hi = z.min(), z.max()
    if hi <= lo:
        return None
    fifth, tenth = 0.2 * (hi - lo), 0.1 * (hi - lo)
    low_width, top_width = np.ptp(skin[z <= lo + fifth, 0]), np.ptp(skin[z >= hi - fifth, 0])
    low_front, top_front = skin[z <= lo + tenth, 1].max(), skin[z >= hi - tenth, 1].max()
    return _Finding(
        not (low_width > top_width and low_front > top_front),
        f"the skin's lowest fifth is {low_width:.0f} mm wide, wider than its highest ({top_width:.0f} mm), and its "
        f"lowest tenth reaches y = {low_front:.1f} mm, in front of its highest (y = {top_front:.1f} mm)",
        "a face that narrows toward the chin and turns back beneath it")


def _findings(skin: np.ndarray, named: Mapping[str, np.ndarray], bones: np.ndarray | None) -> list[_Finding]:
    found = [_front(skin), _covers_bones(skin, bones), _jaws(named), _rami(named), _sides(named)]
    if found[2] is None:
        found.append(_chin(skin))
    return [f for f in found if f is not None]


def _candidates() -> list[np.ndarray]:
    """Every signed permutation of the axes but the identity, the simplest first: fewer axes
    moved, then fewer negated, then x kept."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            m = np.zeros((3, 3))
            m[range(3), perm] = signs
            moved = sum(p != i for i, p in enumerate(perm))
            if moved or min(signs) < 0:
                out.append(((moved, signs.count(-1.0), signs[0] < 0), m))
    return [m for _, m in sorted(out, key=lambda item: item[0])]


def _as_points(a) -> np.ndarray:
    p = np.asarray(a, dtype=float).reshape(-1, 3)
    return p[np.isfinite(p).all(axis=1)]


def check_anatomical_axes(skin_points, bone_points=None, *, axes: str = "toolkit", source: str = "the face") -> None:
    """Refuse a face that is not in the toolkit's axes (x left, y anterior, z superior), judged
    from its anatomy (the criteria in the module docstring), with the conversion that fits.

    Parameters
    ----------
    skin_points : (n, 3) float, mm: the skin, or the whole closed surface of the soft tissue
    bone_points : (k, 3) float mm, or a mapping of segment name (``lefort``, ``distal``,
        ``proximal_left``, ``proximal_right``, ``skull``) -> its points ``(k_s, 3)`` mm; points
        under another name are bone without a place of its own. None: the skin alone
    axes : the axes the points were converted from (:data:`AXES`), for the remedy named
    source : what the points are, for the message (a file name)

    Raises
    ------
    AxesError naming each criterion that fails (what was found, what was expected) and the
    ``axes=`` value (command line ``--axes``) under which the face passes, or the mapping of
    coordinates that would make it pass when no ``axes`` value gives it.
    """
    declared = axes_matrix(axes)
    skin = _as_points(skin_points)
    if len(skin) < 4:
        raise AxesError(f"{source}: {len(skin)} skin points; expected a face's skin to judge its axes from")
    if bone_points is None:
        named = {}
    elif isinstance(bone_points, Mapping):
        named = {k: p for k, v in bone_points.items() if len(p := _as_points(v))}
    else:
        named = {"bone": _as_points(bone_points)}
    bones = np.concatenate(list(named.values())) if named else None
    failed = [f for f in _findings(skin, named, bones) if not f.holds]
    if not failed:
        return
    fix = next((m for m in _candidates()
                if all(f.holds for f in _findings(skin @ m.T, {k: v @ m.T for k, v in named.items()},
                                                   None if bones is None else bones @ m.T))), None)
    what = "; ".join(f"{f.found} (expected {f.expected})" for f in failed)
    raise AxesError(f"{source} is not in the toolkit's axes ({_DESCRIBED['toolkit']}): {what}. "
                    f"{_remedy(fix, declared, sides='proximal_left' in named and 'proximal_right' in named)}")


def _remedy(fix: np.ndarray | None, declared: np.ndarray, sides: bool) -> str:
    """What to do: the ``axes`` value under which the anatomy fits, else the mapping that does."""
    if fix is None:
        return ("No mirror or exchange of the axes makes it a face: check that it is a face's soft tissue (and its "
                "bones), in mm")
    total = fix @ declared  # file coordinates -> the toolkit's
    options = [total] if sides else [total, np.diag([-1.0, 1.0, 1.0]) @ total]
    for m in options:
        for name, signs in _SIGNS.items():
            if np.array_equal(m, np.diag(signs)):
                unsure = "" if m is total else (" (a left-right mirror cannot be told from the face without the "
                                                "proximal segments: check x)")
                if name == "toolkit":
                    return (f"The anatomy fits the files as they are{unsure}: read them with axes=\"toolkit\" "
                            "(command line: --axes toolkit, the default)")
                return (f"The anatomy fits the files read in {name} axes ({_DESCRIBED[name]}){unsure}: pass "
                        f"axes=\"{name}\" (command line: --axes {name}) to convert")
    names = ("x", "y", "z")
    terms = []
    for row in total:
        k = int(np.flatnonzero(row)[0])
        terms.append(("-" if row[k] < 0 else "") + names[k])
    return (f"The anatomy fits toolkit (x, y, z) = ({', '.join(terms)}) of the files' coordinates, which no axes "
            f"value gives ({', '.join(AXES)}): convert the files to {_DESCRIBED['toolkit']} first")


def skin_points(mesh: Mesh) -> np.ndarray:
    """The skin of a face mesh ``(n, 3)`` mm: its node set ``skin``, or its boundary nodes."""
    ids = mesh.node_sets.get("skin")
    if ids is None or not len(ids):
        from toolkit.common.meshes.topology import boundary_face_blocks

        ids = np.unique(np.concatenate([f.ravel() for f in boundary_face_blocks(mesh.cells).values()]))
    return mesh.points[ids]


def check_mesh_axes(mesh: Mesh, bones: Mapping | None = None, *, axes: str = "toolkit", source: str = "the face mesh"):
    """:func:`check_anatomical_axes` on a face mesh: its skin (node set ``skin``, or the boundary),
    the nodes lying on each bony segment (:data:`SEGMENT_SETS`; the set ``bone`` as bone without a
    place) and ``bones`` (segment name -> bone surface points ``(k, 3)`` mm, or a tri3 Mesh), which
    replace the sets of their segments."""
    named = {k: mesh.points[np.concatenate([mesh.node_sets[s] for s in sets if s in mesh.node_sets])]
             for k, sets in SEGMENT_SETS.items() if any(s in mesh.node_sets for s in sets)}
    if not named and "bone" in mesh.node_sets:
        named["bone"] = mesh.points[mesh.node_sets["bone"]]
    for k, v in dict(bones or {}).items():
        named[k] = v.points if isinstance(v, Mesh) else v
    check_anatomical_axes(skin_points(mesh), named, axes=axes, source=source)
