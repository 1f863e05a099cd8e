"""Procedural face and ball phantoms (no patient data exists here).

Axes, in mm: ``x`` lateral (patient's left positive; the midsagittal plane is
``x = 0``), ``y`` anterior (out of the face), ``z`` superior; ``z = 0`` is the
occlusal plane, where the mouth slit lies.

**Face (hexahedral, static workflow).** A structured shell on a smooth skull-like
inner surface ``S(theta, z)`` (maxilla above the occlusal plane, mandible below):
``u`` runs ear to ear (``theta``), ``v`` chin to infraorbital (``z``), ``w`` bone
to skin. Nodes through the thickness are ``S + w * t(theta, z) * n`` with ``n``
the outward unit normal of the bone surface and ``t`` the soft-tissue thickness
(about 10-17 mm, thicker at the lips and cheeks, plus a nose bump). The mouth
slit is a row of duplicated nodes across the full thickness between the
commissures: the upper-lip elements use one copy, the lower-lip elements the
other, so no element connects the lips; with ``mouth_open = 0`` the two faces
touch, otherwise they gap (lips apart, teeth together: the gap grows from 0 at
the bone to ``mouth_open`` at the skin).

Node sets (boundary types, pairwise disjoint): ``fixed`` (top row near the
infraorbital line, posterior edges, and the bone-side nodes above the Le Fort I
cut), ``maxilla`` (bone-side nodes attached to the Le Fort I segment, which ends
laterally at the pterygomaxillary junction), ``mandible``
(bone-side nodes attached to the distal mandible), ``mucosa_sliding`` (bone-side
nodes of the vestibule, which slide on the teeth and alveolus, and of the tissue
over the ramus, which slides on the proximal segments), ``lip_sliding`` (both faces
of the mouth slit). ``mucosa_lefort``, ``mucosa_distal``, ``mucosa_proximal_left``
and ``mucosa_proximal_right`` split the mucosa by the segment it slides on. Region
sets: ``skin`` (outer surface), ``bone`` (inner surface), ``upper_lip_face`` and
``lower_lip_face``. Element set ``lip_muscle`` (orbicularis oris); cell field
``fibre_direction`` (the local superior-inferior unit vector of every element).

The bony segments (``lefort``, ``distal``, ``proximal_left``, ``proximal_right``)
are triangle surfaces of the bone surface, built on the mesh's own grid lines so
that attached and sliding nodes lie exactly on them, with their pivots (the
condyles for the proximal segments).

**Face (tetrahedral, impact workflow).** The same geometry on its own grid
(``~10,000`` elements at ``paper`` resolution, like the impact paper's 9,871 C3D10), each
hexahedron split into 6 tetrahedra; ``tet4`` or ``tet10``. Node set ``fixed`` is
the lower part of the face (``z`` below ``lower_fixed_fraction`` of the height
above the menton).

**Ball.** A tetrahedral ball of radius 110 mm (size-5 football), built by mapping
a cube grid radially onto the sphere, with node set ``surface``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields
from types import MappingProxyType

import numpy as np

from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import TET_EDGES, kuhn_tets, tet10_from_tet4
from toolkit.common.papers import BALL_RADIUS, ball_density

__all__ = [
    "FaceShape",
    "BoneSegment",
    "FacePhantom",
    "face_hex",
    "face_tet",
    "ball",
    "ball_density",
    "block",
    "FACE_RESOLUTIONS",
    "TET_RESOLUTIONS",
    "BALL_RESOLUTIONS",
    "BOUNDARY_SETS",
]

#: (n_u, n_v, n_w) elements ear-to-ear, chin-to-infraorbital, bone-to-skin
FACE_RESOLUTIONS: Mapping[str, tuple[int, int, int]] = MappingProxyType(
    {"coarse": (20, 11, 2), "paper": (38, 25, 3), "fine": (100, 70, 6)}
)
TET_RESOLUTIONS: Mapping[str, tuple[int, int, int]] = MappingProxyType(
    {"coarse": (16, 9, 2), "paper": (26, 16, 4), "fine": (52, 32, 6)}
)
#: cube-grid cells per half axis of the ball
BALL_RESOLUTIONS: Mapping[str, int] = MappingProxyType({"coarse": 3, "paper": 8, "fine": 12})

#: node sets that are boundary types and must be pairwise disjoint
BOUNDARY_SETS = ("fixed", "maxilla", "mandible", "mucosa_sliding", "lip_sliding")

_THETA_MAX = np.deg2rad(80.0)  # half-angle of the arch covered by the face
_MOUTH_FRACTION = 0.6  # fraction of the height below the occlusal plane
_MANDIBLE_ATTACHED_FRACTION = 0.3  # inferior part of the mandible height whose tissue is attached
_MAXILLA_ATTACHED_DEG = 40.0  # half-angle of the anterior maxilla whose tissue stays attached
_POSTERIOR_MARGIN = 10.0  # mm above the condyles where the posterior cut starts to be held


@dataclass(frozen=True)
class FaceShape:
    """Shape parameters of a face phantom ("subject"); all in mm.

    The documented ranges are those over which every element is checked to have a
    positive Jacobian (``tests/common/test_phantom.py``); values outside raise.

    Attributes
    ----------
    face_width : skin width ear to ear at the posterior edges, [100, 140]
    face_height : menton to infraorbital line, [80, 100]
    tissue_thickness : base soft-tissue thickness (cheeks +3, lips + protrusion), [9, 13]
    lip_protrusion : extra thickness at the lips, [0, 6]
    mouth_open : lip gap at the skin, 0 for closed (touching) lips, [0, 12]
    nose_height : height of the subnasal bump, [0, 14]
    """

    face_width: float = 120.0
    face_height: float = 90.0
    tissue_thickness: float = 11.0
    lip_protrusion: float = 4.0
    mouth_open: float = 0.0
    nose_height: float = 10.0

    RANGES = MappingProxyType(
        {
            "face_width": (100.0, 140.0),
            "face_height": (80.0, 100.0),
            "tissue_thickness": (9.0, 13.0),
            "lip_protrusion": (0.0, 6.0),
            "mouth_open": (0.0, 12.0),
            "nose_height": (0.0, 14.0),
        }
    )

    def __post_init__(self):
        for f in fields(self):
            value = float(getattr(self, f.name))
            lo, hi = self.RANGES[f.name]
            if not np.isfinite(value) or not lo <= value <= hi:
                raise ValueError(
                    f"FaceShape.{f.name} = {value!r} mm is outside the validated range [{lo}, {hi}] mm"
                    + (" (a value in metres?)" if 0 < value < 1 else "")
                )
            object.__setattr__(self, f.name, value)

    @classmethod
    def sample(cls, seed: int | np.random.Generator, mouth_open: bool = False) -> FaceShape:
        """A random subject with every parameter uniform in its range.

        ``mouth_open=False`` keeps the lips closed (the usual pre-operative scan).
        """
        rng = np.random.default_rng(seed)
        values = {k: rng.uniform(*r) for k, r in cls.RANGES.items()}
        if not mouth_open:
            values["mouth_open"] = 0.0
        return cls(**values)


@dataclass(frozen=True, eq=False)
class BoneSegment:
    """A rigid bony segment: a triangulated bone surface and its pivot.

    Attributes
    ----------
    name : ``lefort``, ``distal``, ``proximal_left`` or ``proximal_right``
    surface : Mesh with one ``tri3`` block, mm; outward normals point into the soft tissue
    pivot : (3,) float, mm — the condyle for proximal segments, the midpoint of the
        condyles for the distal mandible, the segment's attachment centroid for Le Fort I
    node_set : name of the face node set rigidly attached to this segment, or None
    sliding_set : name of the node set of mucosa nodes that slide on this segment
    """

    name: str
    surface: Mesh
    pivot: np.ndarray
    node_set: str | None
    sliding_set: str | None = None


@dataclass(frozen=True, eq=False)
class FacePhantom:
    """A hexahedral face phantom with its bony segments.

    Attributes
    ----------
    mesh : Mesh (hex8), mm, with the node/element sets of the module docstring
    segments : mapping name -> BoneSegment
    condyles : (2, 3) float, mm — left (x > 0) and right condyle centres
    shape : FaceShape
    resolution : name or (n_u, n_v, n_w)
    """

    mesh: Mesh
    segments: Mapping[str, BoneSegment]
    condyles: np.ndarray
    shape: FaceShape
    resolution: str | tuple[int, int, int]


# --------------------------------------------------------------------- geometry
class _Geometry:
    """The analytic bone surface, thickness field and normals of one subject."""

    def __init__(self, shape: FaceShape):
        self.shape = shape
        h = shape.face_height
        self.z_bot = -_MOUTH_FRACTION * h
        self.z_top = (1.0 - _MOUTH_FRACTION) * h
        self.z_lefort = 0.6 * self.z_top  # Le Fort I cut (above: the immobile skull)
        self.z_condyle = 0.6 * self.z_top  # condyles (the proximal segments' pivots)
        self.z_vest_up = 10.0 * h / 90.0  # upper vestibule depth
        self.z_vest_low = -12.0 * h / 90.0
        # degloved anterior mandible: the tissue slides on the distal segment from here up
        # (the lip-sliding paper extends its sliding region the same way); only the inferior part is attached
        self.z_mandible_attached = self.z_bot + _MANDIBLE_ATTACHED_FRACTION * -self.z_bot
        self.theta_osteo = np.deg2rad(50.0)  # sagittal split, molar region
        self.theta_maxilla = np.deg2rad(55.0)  # posterior end of the Le Fort I segment
        # the soft tissue stays attached to the anterior maxilla (nasal base, upper lip); the
        # degloved lateral walls, back to the pterygomaxillary junction, let it slide
        self.theta_maxilla_attached = np.deg2rad(_MAXILLA_ATTACHED_DEG)
        t_cheek = shape.tissue_thickness + 3.0
        self.a0 = shape.face_width / (2.0 * np.sin(_THETA_MAX)) - t_cheek
        h = shape.face_height
        self._pog = self.z_bot + 0.2 * h  # pogonion (chin prominence)

    @staticmethod
    def _smoothstep(s):
        s = np.clip(s, 0.0, 1.0)
        return s * s * (3.0 - 2.0 * s), 6.0 * s * (1.0 - s)

    def _bumps(self, z):
        """Anterior projection of the bone on the midline, and its z-derivative, mm.

        Smooth Gaussian bumps (chin prominence, incisors, anterior nasal spine) and a
        roll-under towards the menton; concave curvature stays below ~1/30 mm^-1 so
        that the thickest tissue cannot fold the offset surface.
        """
        z = np.asarray(z, dtype=float)
        h = self.shape.face_height
        b, db = np.full_like(z, 42.0), np.zeros_like(z)
        for amp, centre, sigma in ((3.5, self._pog, 0.17 * h), (3.5, 0.0, 0.12 * h), (1.5, 0.7 * self.z_top, 0.1 * h)):
            g = amp * np.exp(-0.5 * ((z - centre) / sigma) ** 2)
            b += g
            db += -g * (z - centre) / sigma**2
        # roll-under below the pogonion: convex (quadratic) all the way to the menton
        span = 0.2 * h
        u = np.clip((self._pog - z) / span, 0.0, None)
        b -= 8.0 * u**2
        db += 16.0 * u / span
        return b, db

    def _b(self, z):
        return self._bumps(z)[0]

    def _db(self, z):
        return self._bumps(z)[1]

    def a(self, z):
        """Lateral half-width of the bone arch, narrowing towards the chin, mm."""
        span = 0.65 * -self.z_bot
        return self.a0 - 5.0 * self._smoothstep((-0.35 * -self.z_bot - np.asarray(z)) / span)[0]

    def da(self, z):
        span = 0.65 * -self.z_bot
        return 5.0 * self._smoothstep((-0.35 * -self.z_bot - np.asarray(z)) / span)[1] / span

    def bone(self, theta, z):
        """Bone surface points, ``(..., 3)`` mm."""
        theta, z = np.broadcast_arrays(theta, z)
        return np.stack([self.a(z) * np.sin(theta), self._b(z) * np.cos(theta), z], axis=-1)

    def normal(self, theta, z):
        """Outward unit normal of the bone surface, ``(..., 3)``."""
        theta, z = np.broadcast_arrays(theta, z)
        s_t = np.stack([self.a(z) * np.cos(theta), -self._b(z) * np.sin(theta), np.zeros_like(z)], axis=-1)
        s_z = np.stack([self.da(z) * np.sin(theta), self._db(z) * np.cos(theta), np.ones_like(z)], axis=-1)
        n = np.cross(s_z, s_t)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def thickness(self, theta, z):
        """Soft-tissue thickness, mm."""
        sh = self.shape
        theta, z = np.broadcast_arrays(theta, z)
        g = lambda v, c, s: np.exp(-0.5 * ((v - c) / s) ** 2)  # noqa: E731
        scale = sh.face_height / 90.0
        lips = ((2.0 + sh.lip_protrusion) * (g(z, 8.0 * scale, 5.0 * scale) + g(z, -8.0 * scale, 5.0 * scale))
                * g(theta, 0.0, 0.4))
        cheeks = 3.0 * (g(theta, 0.9, 0.35) + g(theta, -0.9, 0.35)) * g(z, 5.0 * scale, 18.0 * scale)
        chin = 1.5 * g(z, -0.65 * -self.z_bot, 8.0 * scale) * g(theta, 0.0, 0.35)
        x = self.a(z) * np.sin(theta)
        nose = sh.nose_height * g(x, 0.0, 9.0) * g(z, self.z_top - 3.0 * scale, 7.0 * scale)
        return sh.tissue_thickness + lips + cheeks + chin + nose

    def point(self, theta, z, w):
        """Soft-tissue point at bone-to-skin fraction ``w`` in [0, 1], ``(..., 3)`` mm."""
        theta, z, w = np.broadcast_arrays(theta, z, w)
        return self.bone(theta, z) + (w * self.thickness(theta, z))[..., None] * self.normal(theta, z)

    def z_levels(self, n_v: int) -> tuple[np.ndarray, int]:
        j_mouth = int(round(_MOUTH_FRACTION * n_v))
        below = np.linspace(self.z_bot, 0.0, j_mouth + 1)
        above = np.linspace(0.0, self.z_top, n_v - j_mouth + 1)
        return np.concatenate([below, above[1:]]), j_mouth

    def opening(self, theta, z, w, theta_c):
        """Vertical displacement that opens the mouth, mm (positive above the slit)."""
        g = self.shape.mouth_open
        if g == 0.0:
            return np.zeros(np.broadcast(theta, z, w).shape)
        lip_height = 20.0 * self.shape.face_height / 90.0
        f = np.clip(1.0 - (theta / theta_c) ** 2, 0.0, None)
        decay = np.where(np.abs(z) < lip_height, 0.5 * (1.0 + np.cos(np.pi * np.abs(z) / lip_height)), 0.0)
        return 0.5 * g * f * w * decay


# ----------------------------------------------------------------- structured grid
@dataclass(frozen=True)
class _Grid:
    """Structured node numbering with the duplicated slit row."""

    points: np.ndarray  # (n_points, 3)
    theta: np.ndarray  # (n_u+1,)
    z: np.ndarray  # (n_v+1,)
    j_mouth: int
    slit_cols: np.ndarray  # column indices whose slit nodes are duplicated
    lower: np.ndarray  # (n_u+1, n_v+1, n_w+1) node ids (lower copy at the slit)
    upper_slit: np.ndarray  # (n_u+1, n_w+1) node ids of the upper copies (= lower outside the slit)
    hexes: np.ndarray  # (n_u, n_v, n_w, 2, 2, 2) corner ids by local bits


def _grid(geom: _Geometry, n_u: int, n_v: int, n_w: int) -> _Grid:
    theta = np.linspace(-_THETA_MAX, _THETA_MAX, n_u + 1)
    z, j_mouth = geom.z_levels(n_v)
    w = np.linspace(0.0, 1.0, n_w + 1)
    commissure = 0.2 * geom.shape.face_width
    x_skin = np.abs(geom.point(theta, 0.0, 1.0)[:, 0])
    slit_cols = np.flatnonzero(x_skin < commissure)
    if slit_cols.size == 0:
        raise ValueError(f"resolution n_u={n_u} is too coarse to open a mouth slit (no column within "
                         f"{commissure:.1f} mm of the midline)")
    # theta of the commissures (first columns outside the slit)
    theta_c = theta[slit_cols[-1] + 1]

    T, Z, W = np.meshgrid(theta, z, w, indexing="ij")
    pts = geom.point(T, Z, W)
    lower = np.arange(T.size).reshape(T.shape)
    n_dup = slit_cols.size * (n_w + 1)
    upper_slit = lower[:, j_mouth, :].copy()
    upper_slit[slit_cols, :] = T.size + np.arange(n_dup).reshape(slit_cols.size, n_w + 1)
    dup_pts = pts[slit_cols, j_mouth, :, :].reshape(-1, 3)
    # open the mouth: upper part (rows above the slit + upper copies) up, lower part down
    dz = geom.opening(T, Z, W, theta_c)
    sign = np.where(Z > 0, 1.0, -1.0)
    pts = pts.copy()
    pts[..., 2] += sign * dz
    dup_dz = geom.opening(T[slit_cols, j_mouth], 0.0, W[slit_cols, j_mouth], theta_c).reshape(-1)
    dup_pts[:, 2] += dup_dz
    points = np.vstack([pts.reshape(-1, 3), dup_pts])

    # hex corners: rows j, j+1; elements just above the slit use the upper copies
    ids_lo = lower.copy()  # for the bottom face of elements
    hexes = np.empty((n_u, n_v, n_w, 2, 2, 2), dtype=np.int64)
    for di in (0, 1):
        for dj in (0, 1):
            for dk in (0, 1):
                hexes[..., di, dj, dk] = ids_lo[di:n_u + di, dj:n_v + dj, dk:n_w + dk]
    hexes[:, j_mouth, :, 0, 0, 0] = upper_slit[:-1, :-1]
    hexes[:, j_mouth, :, 1, 0, 0] = upper_slit[1:, :-1]
    hexes[:, j_mouth, :, 0, 0, 1] = upper_slit[:-1, 1:]
    hexes[:, j_mouth, :, 1, 0, 1] = upper_slit[1:, 1:]
    return _Grid(points, theta, z, j_mouth, slit_cols, lower, upper_slit, hexes)


def _hex_connectivity(corners: np.ndarray) -> np.ndarray:
    """VTK hex8 order from corners indexed [i, j, k] by local (u, v, w) bits.

    Local axes (u, v, w) = (ear-to-ear, chin-to-top, bone-to-skin); the frame
    (u, v, w) is left-handed in space (u runs right to left seen from the front),
    so the VTK x/y roles are given to (v, u) to keep positive volumes.
    """
    c = corners.reshape(-1, 2, 2, 2)
    # VTK: 0:(0,0,0) 1:(1,0,0) 2:(1,1,0) 3:(0,1,0) 4..7 same at k=1, with (x, y) = (v, u)
    order = [(0, 0, 0), (0, 1, 0), (1, 1, 0), (1, 0, 0), (0, 0, 1), (0, 1, 1), (1, 1, 1), (1, 0, 1)]
    return np.stack([c[:, i, j, k] for (i, j, k) in order], axis=1)


def _segment_surface(geom: _Geometry, theta: np.ndarray, z: np.ndarray) -> Mesh:
    """Triangulated bone surface on the tensor grid ``theta x z`` (normals outward)."""
    T, Z = np.meshgrid(theta, z, indexing="ij")
    pts = geom.bone(T, Z).reshape(-1, 3)
    nt, nz = T.shape
    ids = np.arange(nt * nz).reshape(nt, nz)
    a, b, c, d = ids[:-1, :-1], ids[1:, :-1], ids[1:, 1:], ids[:-1, 1:]
    tris = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    # orient so the normals point out of the bone (towards the soft tissue)
    x = pts[tris]
    nrm = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    out = geom.normal(T[:-1, :-1].reshape(-1), Z[:-1, :-1].reshape(-1))
    out = np.concatenate([out, out])
    flip = np.einsum("ij,ij->i", nrm, out) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return Mesh(pts, {"tri3": tris})


def _extend(grid_values: np.ndarray, lo: float, hi: float, margin_cells: int = 2) -> np.ndarray:
    """Grid lines of ``grid_values`` within [lo, hi], plus ``margin_cells`` beyond each end."""
    step = np.diff(grid_values)
    inside = grid_values[(grid_values >= lo - 1e-9) & (grid_values <= hi + 1e-9)]
    before = inside[0] - np.arange(margin_cells, 0, -1) * step[0]
    after = inside[-1] + np.arange(1, margin_cells + 1) * step[-1]
    return np.concatenate([before, inside, after])


# --------------------------------------------------------------------- public API
def _resolve(resolution, table, what):
    if isinstance(resolution, str):
        if resolution not in table:
            raise ValueError(f"unknown {what} resolution {resolution!r}; expected one of {list(table)} or a tuple")
        return table[resolution]
    return resolution


def face_hex(resolution: str | tuple[int, int, int] = "coarse", shape: FaceShape | None = None) -> FacePhantom:
    """The hexahedral face phantom for the static (orthognathic) workflow.

    Parameters
    ----------
    resolution : ``coarse`` (~770 nodes), ``paper`` (~4,100 nodes, the PointNet++ paper has
        3,960), ``fine`` (~50,400 nodes, 6 element layers), or ``(n_u, n_v, n_w)``
        element counts.
    shape : FaceShape, default the nominal subject

    Returns
    -------
    FacePhantom
        ``mesh.points`` is ``(n_points, 3)`` mm; see the module docstring for sets.
    """
    shape = shape or FaceShape()
    n_u, n_v, n_w = (int(v) for v in _resolve(resolution, FACE_RESOLUTIONS, "face"))
    if n_u < 6 or n_v < 5 or n_w < 1:
        raise ValueError(f"resolution {(n_u, n_v, n_w)} is too coarse; expected n_u >= 6, n_v >= 5, n_w >= 1")
    geom = _Geometry(shape)
    g = _grid(geom, n_u, n_v, n_w)
    hexes = _hex_connectivity(g.hexes)
    node_sets = _face_node_sets(geom, g)
    fibre, lip_muscle = _lip_muscle(g, hexes, shape, (n_u, n_v, n_w))
    mesh = Mesh(
        g.points,
        {"hex8": hexes},
        node_sets=node_sets,
        element_sets={"lip_muscle": lip_muscle},
        cell_data={"fibre_direction": fibre},
    )
    segments, condyles = _bony_segments(geom, g, shape, g.points[node_sets["maxilla"]].mean(axis=0))
    return FacePhantom(mesh, MappingProxyType(segments), condyles, shape, resolution)


def _face_node_sets(geom: _Geometry, g: _Grid) -> dict:
    """The boundary node sets of the module docstring on the grid ``g``: name -> (k,) int."""
    n_points = g.points.shape[0]
    all_ids = np.concatenate([g.lower.reshape(-1), g.upper_slit[g.slit_cols].reshape(-1)])
    nu1, nv1, nw1 = g.lower.shape
    I, J, K = np.meshgrid(np.arange(nu1), np.arange(nv1), np.arange(nw1), indexing="ij")
    grid_ijk = np.stack([I, J, K], axis=-1).reshape(-1, 3)
    dup_ijk = np.stack(np.meshgrid(g.slit_cols, [g.j_mouth], np.arange(nw1), indexing="ij"), axis=-1).reshape(-1, 3)
    ijk = np.vstack([grid_ijk, dup_ijk])  # row = node id (lower ids are 0..N-1, then duplicates)
    assert np.array_equal(all_ids, np.arange(n_points))
    i, j, k = ijk.T
    theta, z = g.theta[i], g.z[j]
    inner = k == 0

    # the model is cut at the infraorbital line (top row) and behind the ramus (posterior
    # edges); the posterior cut is held only above the condyles, below which the ramus moves
    posterior = ((i == 0) | (i == nu1 - 1)) & (z >= geom.z_condyle + _POSTERIOR_MARGIN - 1e-9)
    fixed = (j == nv1 - 1) | posterior
    # Le Fort I degloving: the mucoperiosteum over the maxilla is elevated up to the
    # infraorbital rim, so above the cut the tissue slides on the immobile skull
    skull = inner & ~fixed & (z > geom.z_lefort + 1e-9)
    in_slit = (j == g.j_mouth) & np.isin(i, g.slit_cols)
    is_upper_copy = np.zeros(n_points, dtype=bool)
    is_upper_copy[g.upper_slit[g.slit_cols].reshape(-1)] = True
    vestibule = (z >= geom.z_vest_low - 1e-9) & (z <= geom.z_vest_up + 1e-9) | (z < 0) & (z > geom.z_mandible_attached)
    over_proximal = np.abs(theta) > geom.theta_osteo
    # the tissue over the ramus slides on the proximal segments: behind the sagittal split the
    # distal and proximal bones move apart by millimetres, which an attachment would tear
    lateral_maxilla = (z > 0) & (z <= geom.z_lefort + 1e-9) & (np.abs(theta) > geom.theta_maxilla_attached) \
        & (np.abs(theta) <= geom.theta_maxilla)
    mucosa = inner & ~fixed & ((z < 0) & over_proximal | vestibule | lateral_maxilla) | skull
    # the Le Fort I segment ends at the pterygomaxillary junction: laterally the tissue lies
    # on the zygoma and ramus and is left free
    maxilla = inner & ~fixed & ~mucosa & (z > 0) & (np.abs(theta) <= geom.theta_maxilla_attached)
    distal = inner & ~fixed & ~mucosa & (z < 0)
    upper_side = (z > 0) | is_upper_copy
    mucosa_on = {
        "lefort": mucosa & upper_side & ~skull,
        "distal": mucosa & ~upper_side & ~over_proximal,
        "proximal_left": mucosa & ~upper_side & over_proximal & (theta > 0),
        "proximal_right": mucosa & ~upper_side & over_proximal & (theta < 0),
        "skull": skull,
    }
    lip = in_slit & ~inner

    return {
        "fixed": np.flatnonzero(fixed),
        "maxilla": np.flatnonzero(maxilla),
        "mandible": np.flatnonzero(distal),
        "mucosa_sliding": np.flatnonzero(mucosa),
        **{f"mucosa_{name}": np.flatnonzero(sel) for name, sel in mucosa_on.items()},
        "lip_sliding": np.flatnonzero(lip),
        "skin": np.flatnonzero(k == nw1 - 1),
        "bone": np.flatnonzero(inner),
        "upper_lip_face": np.flatnonzero(in_slit & is_upper_copy),
        "lower_lip_face": np.flatnonzero(in_slit & ~is_upper_copy),
    }


def _lip_muscle(g: _Grid, hexes: np.ndarray, shape: FaceShape,
                counts: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Per-element fibre direction ``(E, 3)`` (superior, along the grid's v lines) and the
    elements of the lip muscle around the mouth slit ``(m,)`` int; ``counts`` are the element
    counts ``(n_u, n_v, n_w)``."""
    n_u, n_v, n_w = counts
    x = g.points[hexes]
    sup = (x[:, [1, 2, 5, 6]] - x[:, [0, 3, 4, 7]]).mean(axis=1)  # +v (superior) edges
    fibre = sup / np.linalg.norm(sup, axis=1, keepdims=True)
    ei, ej, _ = np.meshgrid(np.arange(n_u), np.arange(n_v), np.arange(n_w), indexing="ij")
    e_theta = 0.5 * (g.theta[ei] + g.theta[ei + 1]).reshape(-1)
    e_z = 0.5 * (g.z[ej] + g.z[ej + 1]).reshape(-1)
    theta_c = g.theta[g.slit_cols[-1] + 1]
    lip_muscle = np.flatnonzero((np.abs(e_theta) < 1.25 * theta_c) & (np.abs(e_z) < 18.0 * shape.face_height / 90.0))
    return fibre, lip_muscle


def _bony_segments(geom: _Geometry, g: _Grid, shape: FaceShape, maxilla_centre: np.ndarray) -> tuple[dict, np.ndarray]:
    """The bony segments on the mesh's grid lines (extended by two cells) and the condyles
    ``(2, 3)`` mm; the Le Fort I segment pivots about ``maxilla_centre`` (3,) mm."""
    th_all = _extend(g.theta, g.theta[0], g.theta[-1])
    pos_condyle = np.array([geom.a0 + 6.0, -18.0 * shape.face_height / 90.0, 0.6 * geom.z_top])
    condyles = np.stack([pos_condyle, pos_condyle * [-1, 1, 1]])
    lefort_surface = _segment_surface(geom, th_all, _extend(g.z, 0.0, geom.z_lefort))
    th_distal = _extend(g.theta, -geom.theta_osteo, geom.theta_osteo)
    z_mand = _extend(g.z, g.z[0], 0.0)
    segments = {
        "lefort": BoneSegment("lefort", lefort_surface, maxilla_centre, "maxilla",
                              "mucosa_lefort"),
        "distal": BoneSegment("distal", _segment_surface(geom, th_distal, z_mand), condyles.mean(axis=0), "mandible",
                              "mucosa_distal"),
        "proximal_left": BoneSegment(
            "proximal_left", _segment_surface(geom, _extend(g.theta, geom.theta_osteo, g.theta[-1]), z_mand),
            condyles[0], None, "mucosa_proximal_left"),
        "proximal_right": BoneSegment(
            "proximal_right", _segment_surface(geom, _extend(g.theta, g.theta[0], -geom.theta_osteo), z_mand),
            condyles[1], None, "mucosa_proximal_right"),
        "skull": BoneSegment("skull", _segment_surface(geom, th_all, _extend(g.z, geom.z_lefort, g.z[-1])),
                             np.zeros(3), None, "mucosa_skull"),
    }
    return segments, condyles


def face_tet(
    resolution: str | tuple[int, int, int] = "coarse",
    order: int = 2,
    shape: FaceShape | None = None,
    lower_fixed_fraction: float = 0.3,
) -> Mesh:
    """The tetrahedral face phantom for the impact workflow.

    Parameters
    ----------
    resolution : ``coarse`` (~1,700 tets), ``paper`` (~10,000 tets like the impact paper's
        9,871 C3D10), ``fine`` (~60,000 tets), or ``(n_u, n_v, n_w)`` hexahedra
        before the 6-tet split.
    order : 1 (``tet4``) or 2 (``tet10``, straight-sided, Abaqus C3D10 equivalent)
    shape : FaceShape
    lower_fixed_fraction : node set ``fixed`` holds every node with ``z`` below
        this fraction of the face height above the menton.

    Returns
    -------
    Mesh with sets ``fixed``, ``skin``, ``bone``, ``upper_lip_face``,
    ``lower_lip_face`` and element set ``lip_muscle``; points ``(n, 3)`` mm.
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (tet4) or 2 (tet10), got {order!r}")
    if not 0.0 < lower_fixed_fraction < 1.0:
        raise ValueError(f"lower_fixed_fraction must be in (0, 1), got {lower_fixed_fraction}")
    res = _resolve(resolution, TET_RESOLUTIONS, "tetrahedral face")
    shape = shape or FaceShape()
    hexface = face_hex(tuple(res), shape).mesh
    geom = _Geometry(shape)
    g = _grid(geom, *res)
    tets = kuhn_tets(g.hexes, g.points)
    hex_of_tet = np.tile(np.arange(g.hexes[..., 0, 0, 0].size), 6)
    points = g.points
    sets = {k: hexface.node_sets[k] for k in ("skin", "bone", "upper_lip_face", "lower_lip_face")}
    z_fix = geom.z_bot + lower_fixed_fraction * shape.face_height
    lip_hex = np.zeros(g.hexes[..., 0, 0, 0].size, dtype=bool)
    lip_hex[hexface.element_sets["lip_muscle"]] = True
    elsets = {"lip_muscle": np.flatnonzero(lip_hex[hex_of_tet])}
    cdata = {"fibre_direction": hexface.cell_data["fibre_direction"][hex_of_tet]}
    if order == 1:
        sets["fixed"] = np.flatnonzero(points[:, 2] < z_fix)
        return Mesh(points, {"tet4": tets}, node_sets=sets, element_sets=elsets, cell_data=cdata)
    points10, tets10 = tet10_from_tet4(points, tets)
    sets = {name: _with_midside_nodes(ids, tets10, points.shape[0]) for name, ids in sets.items()}
    sets["fixed"] = np.flatnonzero(points10[:, 2] < z_fix)
    return Mesh(points10, {"tet10": tets10}, node_sets=sets, element_sets=elsets, cell_data=cdata)


def _with_midside_nodes(ids: np.ndarray, tets10: np.ndarray, n_corner_nodes: int) -> np.ndarray:
    """Extend a node set of corner nodes by the mid-edge nodes whose two ends are in it."""

    member = np.zeros(n_corner_nodes, dtype=bool)
    member[ids] = True
    mids, first = np.unique(tets10[:, 4:].reshape(-1), return_index=True)
    ends = tets10[:, TET_EDGES].reshape(-1, 2)[first]
    return np.concatenate([ids, mids[member[ends[:, 0]] & member[ends[:, 1]]]])


def ball(radius: float = BALL_RADIUS, resolution: str | int = "coarse", order: int = 2, centre=(0.0, 0.0, 0.0)) -> Mesh:
    """A tetrahedral ball (size-5 football: radius 110 mm).

    A cube grid of ``2n`` cells per axis is mapped radially onto the ball
    (``p -> R * |p|_inf * p / |p|_2``); each cell is split into 6 tetrahedra along
    the diagonal pointing away from the centre, so that no tetrahedron straddles
    the planes where the map has a kink.

    Parameters
    ----------
    radius : mm
    resolution : ``coarse`` (n=3, 1,296 tets), ``paper`` (n=8, 24,576 tets; the impact paper
        used 20,695 C3D10), ``fine`` (n=12), or the integer n
    order : 1 (``tet4``) or 2 (``tet10``; mid-edge nodes on the surface are
        projected onto the sphere)
    centre : (3,) mm

    Returns
    -------
    Mesh with node set ``surface``.
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 (tet4) or 2 (tet10), got {order!r}")
    if not radius > 0:
        raise ValueError(f"radius must be positive, got {radius} mm")
    n = int(_resolve(resolution, BALL_RESOLUTIONS, "ball"))
    if n < 1:
        raise ValueError(f"ball resolution n must be >= 1, got {n}")
    s = np.linspace(-1.0, 1.0, 2 * n + 1)
    P = np.stack(np.meshgrid(s, s, s, indexing="ij"), axis=-1).reshape(-1, 3)
    ids = np.arange(P.shape[0]).reshape((2 * n + 1,) * 3)
    norm2 = np.linalg.norm(P, axis=1)
    scale = np.divide(np.abs(P).max(axis=1), norm2, out=np.zeros_like(norm2), where=norm2 > 0)
    pts = radius * P * scale[:, None]
    # cells with local axes reflected so that local (0,0,0) is the corner nearest the centre
    c = np.arange(2 * n)
    ci, cj, ck = np.meshgrid(c, c, c, indexing="ij")
    corners = np.empty(ci.shape + (2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                ii = np.where(ci < n, ci + 1 - a, ci + a)
                jj = np.where(cj < n, cj + 1 - b, cj + b)
                kk = np.where(ck < n, ck + 1 - d, ck + d)
                corners[..., a, b, d] = ids[ii, jj, kk]
    tets = kuhn_tets(corners, pts)
    used = np.unique(tets)
    renumber = np.full(pts.shape[0], -1, dtype=np.int64)
    renumber[used] = np.arange(used.size)
    pts, tets = pts[used], renumber[tets]
    on_surface = np.isclose(np.abs(P[used]).max(axis=1), 1.0)
    if order == 2:
        n0 = pts.shape[0]
        pts, tets = tet10_from_tet4(pts, tets)
        surface = _with_midside_nodes(np.flatnonzero(on_surface), tets, n0)
        # every edge joining two surface nodes lies on a boundary face (the split
        # diagonals point outwards), so projecting its midpoint onto the sphere is exact
        mid = surface[surface >= n0]
        pts[mid] *= radius / np.linalg.norm(pts[mid], axis=1, keepdims=True)
        on_surface = np.zeros(pts.shape[0], dtype=bool)
        on_surface[surface] = True
    ctype = "tet10" if order == 2 else "tet4"
    return Mesh(pts + np.asarray(centre, dtype=float), {ctype: tets}, node_sets={"surface": np.flatnonzero(on_surface)})


def block(axes, cell_type: str = "hex8", jitter: float = 0.0, seed: int | None = None) -> Mesh:
    """A box meshed on the tensor grid ``axes`` (three 1-D coordinate arrays, mm).

    ``hex8`` cells, or each hexahedron split into 6 conforming Kuhn tetrahedra (``tet4``;
    ``tet10`` adds straight mid-edge nodes). ``jitter`` moves every node randomly by up to
    that many mm (reproducible with ``seed``) — the distorted meshes of patch tests.
    """
    axes = [np.asarray(a, dtype=float) for a in axes]
    if len(axes) != 3 or any(a.ndim != 1 or a.size < 2 or np.any(np.diff(a) <= 0) for a in axes):
        raise ValueError("axes must be three increasing 1-D arrays of at least 2 coordinates (mm)")
    n = tuple(a.size - 1 for a in axes)
    P = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    if jitter:
        P = P + np.random.default_rng(seed).uniform(-jitter, jitter, size=P.shape)
    ids = np.arange(P.shape[0]).reshape(tuple(k + 1 for k in n))
    corners = np.empty(n + (2, 2, 2), dtype=np.int64)
    for a in (0, 1):
        for b in (0, 1):
            for d in (0, 1):
                corners[..., a, b, d] = ids[a:n[0] + a, b:n[1] + b, d:n[2] + d]
    corners = corners.reshape(-1, 2, 2, 2)
    if cell_type == "hex8":
        order = [(0, 0, 0), (1, 0, 0), (1, 1, 0), (0, 1, 0), (0, 0, 1), (1, 0, 1), (1, 1, 1), (0, 1, 1)]
        return Mesh(P, {"hex8": np.stack([corners[:, i, j, k] for i, j, k in order], axis=1)})
    if cell_type not in ("tet4", "tet10"):
        raise ValueError(f"cell_type must be hex8, tet4 or tet10, got {cell_type!r}")
    tets = kuhn_tets(corners, P)
    if cell_type == "tet10":
        P, tets = tet10_from_tet4(P, tets)
    return Mesh(P, {cell_type: tets})
