"""From a patient's segmented surfaces to a labelled tetrahedral face mesh.

:func:`mesh_face` runs the stages in order, each timed in the report:

1. **read**: the tissue surface and the bone surfaces (STL, OBJ, PLY, VTK, VTU, OFF; unit
   check and ``units`` conversion), the tissue repaired into a closed outward surface
   (:func:`~toolkit.mesh.surface.closed_surface`), the surfaces and commissures converted from
   ``axes`` (:mod:`toolkit.common.meshes.axes`), each bone oriented toward the tissue, every bone
   checked to lie against the tissue (within the contact distance) and the anatomy checked to be
   in the toolkit's axes (:func:`~toolkit.common.meshes.axes.check_anatomical_axes`);
2. **mesh**: linear tetrahedra of edge length about ``size_mm``
   (:func:`~toolkit.mesh.backends.tetrahedralize`);
3. **mouth** (with commissures): the slit cut between them (:mod:`toolkit.mesh.mouth`);
4. **label**: node sets by the rules (:mod:`toolkit.mesh.labels`, :mod:`toolkit.mesh.rules`);
   a moving segment ruled to carry tissue that carries less than ``min_carried_mm2`` fails here;
5. **order**: quadratic tetrahedra (``order=2``: mid-edge nodes, straight sides), the sets
   extended to the mid-edge nodes of their boundary edges;
6. **quality**: minimum scaled Jacobian and the dihedral angles of the result.

The result (:class:`MeshedFace`) writes itself as VTU (or Abaqus ``.inp``) with its sets,
``labels.json`` (counts, what each segment carries, quality, repairs, rules, times, the estimate
made before meshing) and ``labels.png`` (the sets in colour, from the front and from inside).
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from toolkit.common.defaults import MESH
from toolkit.common.errors import ToolkitError
from toolkit.common.fem.fibres import with_lip_fibres
from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.axes import axes_matrix, check_anatomical_axes, mesh_to_toolkit, to_toolkit
from toolkit.common.meshes.io import atomic_path, write
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.surfaces import orient_surface, read_surface
from toolkit.common.meshes.topology import boundary_faces, lumped_boundary_area, tet10_from_tet4, unique_edges
from toolkit.common.plotting import render
from toolkit.mesh.backends import DEFAULT, tetrahedralize
from toolkit.mesh.budget import available_memory_gib, estimate_size, finest_fitting_size
from toolkit.mesh.rules import SEGMENTS, LabelRules, read_rules
from toolkit.mesh.surface import closed_surface, read_tissue_surface

__all__ = ["MeshedFace", "mesh_face", "carried_report", "FaceInputError", "dihedral_angles", "mid_edge_lookup"]



class FaceInputError(ToolkitError, ValueError):
    """Surfaces or options that cannot make a face mesh."""


@dataclass(frozen=True)
class MeshedFace:
    """A labelled face mesh and what made it.

    mesh : tet4 or tet10 :class:`~toolkit.common.meshes.mesh.Mesh` (mm) with the node sets of the
        static workflow and, with a mouth, the element set ``lip_muscle`` and the cell field
        ``fibre_direction`` (:func:`toolkit.common.fem.fibres.superior_fibres`)
    bones : segment name -> its ``tri3`` surface (mm), oriented toward the tissue
    report : counts, quality, repairs, rules and stage times (``labels.json``)
    """

    mesh: Mesh
    bones: Mapping[str, Mesh]
    report: dict = field(default_factory=dict)

    def write(self, path, *, image: bool = True) -> dict[str, Path]:
        """Write the mesh to ``path`` (``.vtu`` or ``.inp``), ``labels.json`` and ``labels.png``
        beside it (atomically each). Returns the paths written."""

        path = Path(path)
        out = {"mesh": path, "labels": path.with_name("labels.json")}
        write(path, self.mesh)
        with atomic_path(out["labels"]) as tmp:
            tmp.write_text(json.dumps(self.report, indent=2) + "\n")
        if image:
            out["image"] = render_labels(self, path.with_name("labels.png"))
        return out

    def summary(self) -> str:
        r = self.report
        q = r["quality"]
        sets = ", ".join(f"{k} {v}" for k, v in r["node_sets"].items())
        return (f"{r['nodes']} nodes, {r['elements']} {r['element_type']} elements; min scaled Jacobian "
                f"{q['min_scaled_jacobian']:.3f}, dihedral angles {q['min_dihedral_deg']:.1f}-"
                f"{q['max_dihedral_deg']:.1f} deg; lips: {r['mouth']['status']}\nsets: {sets}")


def dihedral_angles(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The six dihedral angles (degrees) of each tetrahedron ``(t, 6)`` (corner nodes)."""
    x = points[tets[:, :4]]
    faces = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # face opposite corner i
    n = np.cross(x[:, faces[:, 1]] - x[:, faces[:, 0]], x[:, faces[:, 2]] - x[:, faces[:, 0]])
    n /= np.linalg.norm(n, axis=2, keepdims=True)
    pairs = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
    cos = -np.einsum("tpk,tpk->tp", n[:, pairs[:, 0]], n[:, pairs[:, 1]])
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def _check_inputs(bones: Mapping, size_mm: float, order: int, commissures) -> None:
    unknown = sorted(set(bones) - set(SEGMENTS))
    if unknown:
        raise FaceInputError(f"unknown bone segments {unknown}; expected some of {list(SEGMENTS)} "
                             "(command line: --bone NAME=FILE)")
    if not bones:
        raise FaceInputError("no bone surface given; expected at least the moving segments of the plan "
                             "(command line: --bone lefort=maxilla.stl --bone distal=mandible.stl)")
    if not (np.isfinite(size_mm) and 0.3 <= size_mm <= 20.0):
        raise FaceInputError(f"size_mm = {size_mm!r}; expected an element edge length of 0.3-20 mm "
                             "(command line: --size)")
    if order not in (1, 2):
        raise FaceInputError(f"order = {order!r}; expected 1 (tet4) or 2 (tet10) (command line: --order)")
    if commissures is not None:
        c = np.asarray(commissures, dtype=float)
        if c.shape != (2, 3) or not np.isfinite(c).all():
            raise FaceInputError(f"commissures = {np.asarray(commissures).tolist()}; expected two points "
                                 "[x, y, z] mm (command line: --commissures X,Y,Z X,Y,Z)")


def _check_budget(surface: Mesh, size_mm: float, order: int, memory_gib: float | None, source: str):
    """The :class:`~toolkit.mesh.budget.SizeEstimate` of meshing ``surface`` at ``size_mm``;
    raises :class:`FaceInputError` when it needs more than ``memory_gib`` (default: available)."""

    tri = surface.cells["tri3"]
    estimate = estimate_size(surface.points, tri, size_mm, order)
    limit = available_memory_gib() if memory_gib is None else float(memory_gib)
    if limit is not None and estimate.peak_gib > limit:
        fits = finest_fitting_size(surface.points, tri, limit, order)
        raise FaceInputError(
            f"{source} at --size {size_mm:g} mm: about {estimate.elements:,} elements and {estimate.nodes:,} nodes, "
            f"which need about {estimate.peak_gib:.1f} GiB to mesh and simulate, more than the {limit:.1f} GiB "
            f"{'available' if memory_gib is None else 'allowed (--memory)'}; --size {fits:g} or coarser fits "
            "(--memory GIB sets the limit)")
    return estimate


def _read_bone(name: str, source, units: str) -> Mesh:

    if isinstance(source, Mesh):
        return source
    return read_surface(source, units=units)


def _check_contact(tissue: Mesh, bones: Mapping[str, Mesh], rules: LabelRules, names: Mapping[str, str]) -> None:
    from toolkit.common.analysis.surface_distance import closest_points

    for name, bone in bones.items():
        d = closest_points(bone.points, tissue.points, tissue.cells["tri3"]).distance
        if d.min() > rules.contact_mm:
            raise FaceInputError(
                f"bone {name} ({names[name]}) lies {d.min():.1f} mm from the tissue surface at its nearest; "
                f"expected it against the tissue's inner side (within contact_mm = {rules.contact_mm:g} mm). "
                "Check that it is in the tissue's axes and units (--units), or raise contact_mm in the "
                "labelling rules (--rules)")


def _edges_of(faces: np.ndarray) -> np.ndarray:
    """Unique sorted edges ``(e, 2)`` of triangles."""

    return unique_edges(faces, REFERENCE_ELEMENTS["tri3"].edges)[0]


def mid_edge_lookup(cells10: np.ndarray):
    """The function that maps corner-node edges ``(k, 2)`` (sorted or not) of a tet10 mesh
    ``cells10 (t, 10)`` to their mid-edge nodes ``(k,)``; the edges must be edges of its cells."""
    cells10 = np.asarray(cells10, dtype=np.int64)
    corner_pairs = np.array([[0, 1], [1, 2], [0, 2], [0, 3], [1, 3], [2, 3]])
    pairs = np.sort(cells10[:, corner_pairs], axis=2).reshape(-1, 2)
    n = int(cells10.max()) + 1
    key, first = np.unique(pairs[:, 0] * n + pairs[:, 1], return_index=True)
    mid_of = cells10[:, 4:].reshape(-1)[first]

    def mid(edges):
        e = np.sort(np.asarray(edges, dtype=np.int64).reshape(-1, 2), axis=1)
        return mid_of[np.searchsorted(key, e[:, 0] * n + e[:, 1])]

    return mid


def _elevate(points: np.ndarray, tets: np.ndarray, node_sets: dict[str, np.ndarray],
             set_faces: Mapping[str, np.ndarray]):
    """tet10 from tet4, each set extended to the mid-edge nodes of the edges of its faces
    (``set_faces[name]``; default the boundary faces) whose two ends are in the set."""

    p10, t10 = tet10_from_tet4(points, tets)
    n4 = points.shape[0]
    mid = mid_edge_lookup(t10)
    boundary = _edges_of(boundary_faces("tet4", tets))
    out = {}
    for name, ids in node_sets.items():
        edges = _edges_of(set_faces[name]) if name in set_faces else boundary
        member = np.zeros(n4, dtype=bool)
        member[ids] = True
        both = member[edges[:, 0]] & member[edges[:, 1]]
        out[name] = np.union1d(ids, mid(edges[both]))
    # a mid-edge node between two segments' mucosa slides on neither: the union is rebuilt
    per_segment = [v for k, v in out.items() if k.startswith("mucosa_") and k != "mucosa_sliding"]
    if "mucosa_sliding" in out:
        out["mucosa_sliding"] = np.unique(np.concatenate(per_segment)) if per_segment else np.zeros(0, np.int64)
    return p10, t10, out


def _pair_lips(points: np.ndarray, cells: np.ndarray, node_sets: dict[str, np.ndarray]):
    """Renumber the lower lip's nodes so that the sorted ``upper_lip_face`` and
    ``lower_lip_face`` pair up index by index at coincident points (the static workflow
    pairs the two faces in that order)."""
    from scipy.spatial import cKDTree

    upper, lower = np.sort(node_sets["upper_lip_face"]), np.sort(node_sets["lower_lip_face"])
    dist, partner = cKDTree(points[lower]).query(points[upper])
    if upper.size != lower.size or np.unique(partner).size != partner.size or dist.max() > 1e-9:
        raise ToolkitError(f"the mouth slit's faces do not pair up ({upper.size} upper, {lower.size} lower nodes, "
                           f"largest gap {dist.max():.2g} mm)")
    perm = np.arange(points.shape[0])
    perm[lower[partner]] = lower  # the partner of upper[i] becomes the i-th lower id
    new_points = np.empty_like(points)
    new_points[perm] = points
    return new_points, perm[cells], {k: np.sort(perm[v]) for k, v in node_sets.items()}


def _lip_muscle(points: np.ndarray, tets: np.ndarray, slit, commissures, rules: LabelRules) -> np.ndarray:
    """Elements within ``lip_muscle_mm`` above or below the slit plane, between the commissures
    and ``lip_muscle_lateral`` of the mouth's width beyond each, no farther behind their line
    than the slit reaches."""
    c = np.asarray(commissures, dtype=float)
    e = (c[1] - c[0]) / slit.width_mm
    x = points[tets[:, :4]].mean(axis=1)
    t = (x - c[0]) @ e / slit.width_mm
    behind = c[0, 1] + t * (c[1, 1] - c[0, 1]) - x[:, 1]
    lateral = rules.lip_muscle_lateral
    return np.flatnonzero((t > -lateral) & (t < 1 + lateral)
                          & (np.abs((x - c[0]) @ slit.normal) <= rules.lip_muscle_mm) & (behind < 15.0))


def carried_report(mesh: Mesh, rules: LabelRules) -> dict:
    """Per labelled segment, what it holds of the tissue: ``attached_nodes`` (its carried set),
    ``attached_area_mm2`` and ``facing_area_mm2`` (lumped boundary areas of the carried set and
    of all the tissue lying on its bone, carried or sliding) and ``carried_share`` (their ratio)."""
    from toolkit.mesh.labels import CARRIED_SETS

    area = lumped_boundary_area(mesh.points, mesh.cells)
    out = {}
    for name in SEGMENTS:
        carried = mesh.node_sets.get(CARRIED_SETS.get(name, ""), np.zeros(0, np.int64))
        sliding = mesh.node_sets.get(f"mucosa_{name}")
        if sliding is None and not carried.size:
            continue
        facing = float(area[np.union1d(carried, np.zeros(0, np.int64) if sliding is None else sliding)].sum())
        held = float(area[carried].sum())
        out[name] = {"attach": rules.segments[name].attach, "attached_nodes": int(carried.size),
                     "attached_area_mm2": round(held, 2), "facing_area_mm2": round(facing, 2),
                     "carried_share": round(held / facing, 4) if facing > 0 else 0.0}
    return out


def _check_carried(segments: Mapping[str, dict], rules: LabelRules, names: Mapping[str, str]) -> None:
    """A moving segment ruled to carry tissue must carry at least ``rules.min_carried_mm2`` and a
    share of at least ``rules.min_carried_share`` of the tissue lying on its bone."""
    for name in ("lefort", "distal"):
        rule = rules.segments[name]
        if name not in names or rule.attach in ("none", "fixed"):
            continue
        got = segments.get(name, {"attached_nodes": 0, "attached_area_mm2": 0.0, "facing_area_mm2": 0.0,
                                  "carried_share": 0.0})
        if got["attached_area_mm2"] < rules.min_carried_mm2 or got["carried_share"] < rules.min_carried_share:
            raise FaceInputError(
                f"segment {name} ({names[name]}) carries {got['attached_nodes']} nodes, {got['attached_area_mm2']:.1f} "
                f"mm^2 of tissue, a share of {got['carried_share']:.3f} of the {got['facing_area_mm2']:.1f} mm^2 lying "
                f"on its bone; expected at least {rules.min_carried_mm2:g} mm^2 (rules key min_carried_mm2) and a "
                f"share of {rules.min_carried_share:g} (rules key min_carried_share): a plan moving it would leave "
                f"the tissue behind. Check that the bone lies against the tissue's inner side in the same axes and "
                f"units, raise contact_mm if the tissue stands off the bone, or choose what it carries with "
                f"segments.{name}.attach in --rules")


def mesh_face(tissue, bones: Mapping, commissures=None, *, size_mm: float = MESH["size_mm"],
              order: int = MESH["order"], backend: str = DEFAULT, rules=None, units: str = "mm",
              axes: str = "toolkit", max_hole_edges: int = 60, threads: int = 1,
              memory_gib: float | None = None) -> MeshedFace:
    """Mesh and label a face from its segmented surfaces (see the module for the stages).

    Parameters
    ----------
    tissue : the soft tissue's closed surface: a file or a ``tri3`` Mesh (mm)
    bones : segment name (``lefort``, ``distal``, ``proximal_left``, ``proximal_right``,
        ``skull``) -> its surface file or ``tri3`` Mesh, as the planning system exports it
        after the virtual osteotomy
    commissures : the two corners of the mouth on the skin ``(2, 3)`` mm; the lips are cut
        between them and slide on each other. None: a closed mouth, no lip sliding
    size_mm : target tetrahedron edge length, mm
    order : 1 (tet4) or 2 (tet10)
    backend : the tetrahedral mesher (:data:`toolkit.mesh.backends.BACKENDS`)
    rules : :class:`~toolkit.mesh.rules.LabelRules`, a TOML file of overrides, or None (defaults)
    units : length unit of the files (``mm``, ``cm``, ``m``, ``um``)
    axes : axes of the tissue, the bones and the commissures, files or Meshes (``toolkit``: x left,
        y anterior, z superior; ``LPS``; ``RAS``: :data:`toolkit.common.meshes.axes.AXES`), converted to
        the toolkit's. A face whose anatomy says other axes is refused
        (:class:`~toolkit.common.meshes.axes.AxesError`, naming the ``axes`` that fits) before meshing
    max_hole_edges : holes of the tissue surface bounded by up to this many edges are closed
    threads : threads the mesher may use (fTetWild). fTetWild's mesh differs from run to run even
        on one thread (its node count among them); keep the written mesh, not the command, as the
        record of a patient's model
    memory_gib : the memory meshing and then simulating a plan may take, GiB (default: what the
        system has available now). Before meshing, the size's elements, nodes and memory are
        estimated from the tissue's volume and area (:mod:`toolkit.mesh.budget`; in ``report``
        under ``estimate``); a size whose estimate exceeds this is refused, naming the finest
        size that fits
    """
    from toolkit.mesh.labels import label_nodes

    _check_inputs(bones, size_mm, order, commissures)
    axes_matrix(axes)
    rules = rules if isinstance(rules, LabelRules) else read_rules(rules)
    names = {k: (Path(v).name if not isinstance(v, Mesh) else "given surface") for k, v in bones.items()}
    times = {}
    t0 = time.perf_counter()
    if isinstance(tissue, Mesh):
        surface, repair = closed_surface(tissue.points, tissue.cells["tri3"], max_hole_edges=max_hole_edges)
        tissue_name = "given surface"
    else:
        surface, repair = read_tissue_surface(tissue, units=units, max_hole_edges=max_hole_edges)
        tissue_name = Path(tissue).name
    surface = mesh_to_toolkit(surface, axes)
    bone_surfaces = {k: mesh_to_toolkit(_read_bone(k, v, units), axes) for k, v in bones.items()}
    if commissures is not None:
        commissures = to_toolkit(commissures, axes)
    _check_contact(surface, bone_surfaces, rules, names)
    estimate = _check_budget(surface, size_mm, order, memory_gib, tissue_name)
    check_anatomical_axes(surface.points, {k: v.points for k, v in bone_surfaces.items()}, axes=axes,
                          source=f"{tissue_name} with its bones ({', '.join(names.values())})")
    times["read_repair"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    points, tets = tetrahedralize(surface.points, surface.cells["tri3"], size_mm, backend=backend, threads=threads)
    # element centroids lie inside the tissue: each bone's normals turn toward them
    centroids = points[tets].mean(axis=1)
    bone_surfaces = {k: orient_surface(v, centroids) for k, v in bone_surfaces.items()}
    times["mesh"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    slit = None
    mouth: dict[str, object] = {"status": "closed mouth: no lip sliding (give the commissures to cut the lips)"}
    if commissures is not None:
        from toolkit.mesh.mouth import cut_mouth

        slit = cut_mouth(points, tets, commissures)
        points, tets = slit.points, slit.tets
        mouth = {"status": f"cut between the commissures ({slit.width_mm:.1f} mm wide), lips slide",
                 "slit_faces": int(slit.faces.shape[0]), "duplicated_nodes": int(slit.upper.size),
                 "commissures_mm": np.asarray(commissures, dtype=float).round(3).tolist()}
    times["mouth"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    exclude = None if slit is None else np.vstack([slit.faces, slit.lower_faces])
    labels = label_nodes(points, tets, bone_surfaces, rules, exclude_faces=exclude)
    node_sets = dict(labels.node_sets)
    element_sets = {}
    if slit is not None:
        node_sets["upper_lip_face"] = np.sort(slit.upper)
        node_sets["lower_lip_face"] = np.sort(slit.lower)
        node_sets["lip_sliding"] = np.sort(np.concatenate([slit.upper, slit.lower]))
        element_sets["lip_muscle"] = _lip_muscle(points, tets, slit, commissures, rules)
    times["label"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    ctype, cells = "tet4", tets
    if order == 2:
        set_faces = {} if slit is None else {"upper_lip_face": slit.faces, "lower_lip_face": slit.lower_faces,
                                             "lip_sliding": np.vstack([slit.faces, slit.lower_faces])}
        points, cells, node_sets = _elevate(points, tets, node_sets, set_faces)
        ctype = "tet10"
    if slit is not None:
        points, cells, node_sets = _pair_lips(points, cells, node_sets)
    mesh = with_lip_fibres(Mesh(points, {ctype: cells}, node_sets=node_sets, element_sets=element_sets))
    times["order"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    sj = mesh.scaled_jacobian()
    dihedral = dihedral_angles(mesh.points, mesh.volume_cells)
    times["quality"] = time.perf_counter() - t0
    if sj.min() <= 0:
        raise ToolkitError(f"the {backend} mesh has {int((sj <= 0).sum())} inverted elements; try another "
                           "backend or size")
    segments = carried_report(mesh, rules)
    _check_carried(segments, rules, names)
    offsets = np.concatenate([v for v in labels.offsets.values()]) if labels.offsets else np.zeros(0)
    report = {
        "tissue": tissue_name, "bones": names, "axes": axes, "backend": backend, "size_mm": float(size_mm),
        "element_type": mesh.volume_type, "nodes": int(mesh.n_points), "elements": int(mesh.n_volume_cells),
        "node_sets": {k: int(len(v)) for k, v in sorted(node_sets.items())},
        "element_sets": {k: int(len(v)) for k, v in element_sets.items()},
        "segments": segments,
        "quality": {"min_scaled_jacobian": float(sj.min()), "p1_scaled_jacobian": float(np.percentile(sj, 1)),
                    "min_dihedral_deg": float(dihedral.min()), "max_dihedral_deg": float(dihedral.max()),
                    "slivers_below_10deg": int((dihedral.min(axis=1) < 10.0).sum())},
        "bone_offset_mm": {"median": float(np.median(offsets)) if offsets.size else 0.0,
                           "p90": float(np.percentile(offsets, 90)) if offsets.size else 0.0,
                           "max": float(offsets.max(initial=0.0))},
        "mouth": mouth, "repair": repair.to_dict(), "rules": rules.to_dict(),
        "seconds": {k: round(v, 3) for k, v in times.items()},
        "estimate": {"elements": estimate.elements, "nodes": estimate.nodes,
                     "mesher_gib": round(estimate.mesher_gib, 2), "simulation_gib": round(estimate.simulation_gib, 2)},
    }
    return MeshedFace(mesh, bone_surfaces, report)


_SHOWN = ("fixed", "maxilla", "mandible", "mucosa_sliding", "lip_sliding", "skin")


def render_labels(face: MeshedFace, path) -> Path:
    """``labels.png``: the node sets in colour, from the front and from inside, side by side."""
    import tempfile

    from matplotlib.figure import Figure
    from matplotlib.image import imread


    sets = {k: face.mesh.node_sets[k] for k in _SHOWN if k in face.mesh.node_sets and k != "skin"}
    fig = Figure(figsize=(12, 5), dpi=100)
    with tempfile.TemporaryDirectory() as tmp:
        for i, camera in enumerate(("front", "inner")):
            png = render(face.mesh, Path(tmp) / f"{camera}.png", camera=camera, node_sets=sets, show_edges=False,
                         title="node sets")
            ax = fig.add_subplot(1, 2, i + 1)
            ax.imshow(imread(png))
            ax.set_axis_off()
    fig.tight_layout()
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    return path
