"""Face surfaces from a head CT: the soft tissue and the bony segments of a virtual osteotomy.

:func:`ct_surfaces` turns a CT volume (:func:`~toolkit.mesh.volume.read_volume`) into what
:func:`~toolkit.mesh.mesh_face` (``toolkit mesh``) takes: the soft tissue's closed surface and the
bone surfaces of the segments ``lefort``, ``distal``, ``proximal_left``, ``proximal_right`` and
``skull``, in the toolkit's axes (x toward the patient's left, y anterior, z superior, mm). Every
rule below is a fact of human anatomy; :class:`~toolkit.mesh.ct_anatomy.CTRules` holds its values
and :mod:`toolkit.mesh.ct_anatomy` applies them.

**Axes.** A CT's header rarely says where the patient's front is, so the anatomy decides:

- *superior*: the slice axis (the last index axis) is the head's long axis, as in an axial series.
  The cranium is the end whose slices hold the larger share of the head inside the bone's outline
  (the brain inside the skull); the neck's slices hold little (the vertebrae);
- *anterior*: of the two in-plane axes and their directions, the one in which the head's outline
  has the most protruding point on the middle third of its height (the nose stands 10-30 mm in
  front of the cheeks; the occiput is round; the ears protrude on both sides alike, so the
  left-right axis shows no difference between its two directions);
- *left*: a face is symmetric, so a mirror cannot be told from it. The index frame keeps the
  handedness the header gives (``space: 3D-left-handed``, or the sign of ``space directions``);
  without one it is taken as right-handed, as the patient frames of DICOM (LPS) and NIfTI (RAS)
  are. Left then follows from anterior and superior. A header with the wrong handedness gives a
  mirrored patient: ``axes=`` sets every direction by hand (``LPI``: index axis 0 toward the
  patient's left, 1 posterior, 2 inferior).

**The face's frame.** x = 0 on the mid-sagittal plane (the middle of the skin's width over the
middle third of the head), the origin at the incisal point (the most anterior tooth on the
occlusal plane near the midline), z turned about x so that the occlusal plane is inclined
``occlusal_tilt_deg`` (10 degrees, anterior end down: its mean inclination to the Frankfort
horizontal, which the CT's resolution does not show; a head lying flexed or extended on the table
is turned upright). The head's yaw and roll on the table are taken as small.

**Segmentation.** Skin is the largest connected piece above ``skin``, its openings narrower than
``closing_mm`` closed (nostrils) and every cavity then enclosed filled (the airway, the mouth and
the sinuses count as inside; the volume's cut ends close the body). Bone is the pieces above
``bone`` of at least ``min_bone_piece`` of the largest (the hyoid and loose calcifications are left
out). Teeth are the densest voxels: above ``teeth``, by default air + 2.4 (bone - air): enamel and
dentine lie well above cortical bone in any scanner's units.

**Landmarks and cuts** (the osteotomy planes are those of the occlusal plane's frame, as a
planning system draws them):

- *nose tip*: the outline's most protruding point (above); *midline*: above;
- *occlusal plane*: of the planes containing the left-right axis, the one through the widest gap
  between the upper and lower teeth (their projections onto its normal, between the 15th and 85th
  percentiles). It separates the maxilla from the mandible where they touch: at the closed teeth;
- *jaws apart*: the mandible and the rest of the skull also touch at the jaw joints. A watershed on
  the CT values, flooded from the mandible's body (bone 12 mm or more below the occlusal plane in
  front of the last molars), the maxilla (8 mm or more above it within the dental arch) and the
  cranium (the top tenth of the volume, bone 15 mm above the Le Fort I plane, the midline bone
  behind the pharynx), meets along the least dense voxels between them: the occlusal gap and the
  joint spaces, which a threshold alone leaves closed at CT resolution. The rami are mirror images:
  bone behind the splits that mirrors the mandible across the midline is mandible (a thin condylar
  neck can flood later than its joint space);
- *Le Fort I*: the plane ``lefort_mm`` above the occlusal plane, parallel to it: above the tooth
  apices (the canine's root reaches about 27 mm above its cusp) and the nasal floor, as the
  osteotomy runs from the piriform aperture to the pterygomaxillary junction. ``lefort`` is the
  non-mandibular bone between it and the teeth in front of the *tuberosity plane*,
  ``tuberosity_mm`` behind the last upper molar (the pterygoid plates stay with the skull);
  ``skull`` is the rest;
- *sagittal splits*: on each side the plane normal to the occlusal plane's anterior direction,
  ``split_mm`` behind the last lower molar: through the ramus. ``distal`` is the mandible below the
  occlusal plane in front of both (body, teeth, chin); ``proximal_left`` and ``proximal_right`` are
  the rest of each side joined to it (ramus, coronoid process, condyle);
- *condyles*: the centre of each proximal segment's top ``condyle_band_mm``;
- *menton*: the distal segment's lowest point within 8 mm of the midline; *ramus lower border*:
  where the mandibular plane touches the rami (below); *chin*: the skin point
  within 5 mm of the midline below the incisal point most anterior-inferior (largest y - z).

**The tissue** is the facial soft-tissue envelope, the model's part of the skin region: the skin
region minus bone, minus what lies behind bone seen from the front (the tongue, the pharynx and
the sinuses are not part of it: the bones move the face through the tissue on their outer side;
gaps up to ``tooth_gap_mm`` between bone above and below, as between the incisors of a mouth
slightly open, hide what lies behind as bone does), within ``depth_mm`` of the skin. The mouth is
closed (:func:`~toolkit.mesh.ct_anatomy.closed_lips`). Its surface is the CT's own isosurface:
the skin at ``skin`` outside, the bone at ``bone`` inside, so the tissue's inner surface lies on
the bones' surfaces. It is cut to the lower face by planes of the face's frame, each capped flat:
*superior* ``superior_mm`` above the Le Fort I plane's highest point on the maxilla (the tissue the
skull holds above the osteotomy, below the orbits), *posterior* through the condyles
(``posterior_mm`` in front; the jaw joints lie just in front of the ear canals), *inferior*
parallel to the mandibular plane, ``inferior_mm`` below the menton (the soft-tissue chin): the
mandibular plane is the line from the menton tangent to the lower border of the rami (the
proximal segments' point it touches: *ramus lower border*), so the cut follows the jaw's lower
border back to the angle and leaves out the neck below it, which a level cut would leave as a thin
wedge between the moving jaw and the held posterior cut. Where the volume ends first, its end cuts
the tissue.

**Mouth.** At CT resolution the lips' slit is not resolved, so no commissures are given: the mouth
is closed, without lip sliding (``toolkit mesh --commissures`` adds them by hand).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

from toolkit.common.meshes.axes import AxesError, check_anatomical_axes
from toolkit.common.meshes.io import atomic_path
from toolkit.common.meshes.mesh import Mesh
from toolkit.mesh import ct_anatomy as anatomy
from toolkit.mesh.ct_anatomy import CTError, CTRules, Frame
from toolkit.mesh.surface import closed_surface
from toolkit.mesh.volume import Volume, read_volume

__all__ = ["CTRules", "CTSurfaces", "CTError", "ct_surfaces", "SEGMENT_NAMES"]

#: the bony segments, in the order ``toolkit mesh`` gives a shared rim to
SEGMENT_NAMES = ("lefort", "distal", "proximal_left", "proximal_right", "skull")


@dataclass(frozen=True)
class CTSurfaces:
    """What :func:`ct_surfaces` found in a CT.

    tissue : closed ``tri3`` surface of the soft tissue, outward, mm (the face's frame)
    bones : segment name -> its ``tri3`` surface, mm
    commissures : (2, 3) mm, or None: the mouth closed (the lips' slit is not resolved)
    report : thresholds, axes, landmarks and cuts (mm, the face's frame), the osteotomy planes (mm,
        the occlusal plane's frame: z its normal, y along it, origin at the incisal point), surface
        sizes, seconds (``ct.json``)
    """

    tissue: Mesh
    bones: dict[str, Mesh]
    commissures: np.ndarray | None
    report: dict = field(default_factory=dict)

    def write(self, folder) -> dict[str, Path]:
        """Write ``tissue.stl``, ``<segment>.stl`` (binary STL) and ``ct.json`` (the report) into
        ``folder``, each atomically. Returns name -> path."""
        import meshio


        folder = Path(folder)
        folder.mkdir(parents=True, exist_ok=True)
        out = {}
        for name, surface in {"tissue": self.tissue, **self.bones}.items():
            out[name] = folder / f"{name}.stl"
            with atomic_path(out[name]) as tmp:
                meshio.write(tmp, meshio.Mesh(surface.points, [("triangle", surface.cells["tri3"])]),
                             file_format="stl", binary=True)
        out["report"] = folder / "ct.json"
        with atomic_path(out["report"]) as tmp:
            tmp.write_text(json.dumps(self.report, indent=2) + "\n")
        return out

    def summary(self) -> str:
        """What was found, in a few lines (mm, the face's frame)."""
        r = self.report
        marks = "; ".join(f"{k} ({', '.join(f'{c:.1f}' for c in v)})" for k, v in r["landmarks_mm"].items() if v)
        planes = ", ".join(f"{k} {v:.1f}" for k, v in r["osteotomy_mm"].items())
        cuts = ", ".join(f"{k} {v:.1f}" for k, v in r["cuts_mm"].items())
        sizes = ", ".join(f"{k} {v['triangles']}" for k, v in r["surfaces"].items())
        return (f"axes {r['axes']['axes']} ({r['axes']['how']}); occlusal plane {r['occlusal_plane']['pitch_deg']:.1f} "
                f"deg in the volume, gap {r['occlusal_plane']['tooth_gap_mm']:.1f} mm between the teeth\n"
                f"landmarks (face frame): {marks}\nosteotomy (occlusal frame): {planes}\ncuts (face frame): {cuts}\n"
                f"triangles: {sizes}\nmouth: {r['mouth']['status']}")


# ------------------------------------------------------------------------------------ surfaces


def _contour(values: np.ndarray, level: float, spacing: np.ndarray, frame: Frame):
    """The isosurface ``values = level`` as pyvista PolyData in ``frame`` (mm), closed at the
    array's ends (padded below the level)."""
    import pyvista as pv

    padded = np.pad(values.astype(np.float32), 1, constant_values=min(float(values.min()), level) - 1.0)
    grid = pv.ImageData(dimensions=padded.shape, spacing=tuple(spacing), origin=tuple(-spacing))
    grid.point_data["f"] = padded.ravel(order="F")
    surface = grid.contour([level], scalars="f", method="flying_edges").triangulate().clean()
    if surface.n_points:
        surface.points = frame(surface.points)
    return surface


def _as_mesh(surface) -> Mesh:
    faces = surface.faces.reshape(-1, 4)[:, 1:] if surface.n_cells else np.zeros((0, 3), np.int64)
    return Mesh(np.asarray(surface.points, dtype=float), {"tri3": np.asarray(faces, dtype=np.int64)})


def _bbox(mask: np.ndarray, pad: int) -> tuple[slice, ...]:
    idx = [np.flatnonzero(mask.any(axis=tuple(j for j in range(3) if j != i))) for i in range(3)]
    return tuple(slice(max(int(i[0]) - pad, 0), min(int(i[-1]) + pad + 1, n)) for i, n in zip(idx, mask.shape))


def _pieces(surface, min_fraction: float):
    """The connected pieces holding at least ``min_fraction`` of the largest one's triangles."""
    if surface.n_cells == 0:
        return surface
    conn = surface.connectivity("all")
    region = np.asarray(conn.cell_data["RegionId"])
    counts = np.bincount(region)
    keep = np.flatnonzero(counts >= min_fraction * counts.max())
    return conn.extract_cells(np.isin(region, keep)).extract_surface(algorithm="dataset_surface").clean()


def _bone_surface(values: np.ndarray, mask: np.ndarray, spacing: np.ndarray, frame: Frame, rules: CTRules) -> Mesh:
    """The CT's bone isosurface on a segment's ``mask``, cut at the mask's border half-way to the
    next voxel (two segments that touch share the cut); pieces under 2 % of the largest left out."""
    sl = _bbox(mask, pad=2)
    v = values[sl].astype(np.float32)
    field_ = np.where(mask[sl], v, np.minimum(v, 2 * rules.bone - v))
    surface = _contour(field_, rules.bone, spacing, frame.shifted([s.start for s in sl], spacing))
    return _as_mesh(_pieces(surface, 0.02))


def _tissue_field(values: np.ndarray, skin: np.ndarray, bone: np.ndarray, spacing: np.ndarray,
                  rules: CTRules) -> tuple[np.ndarray, np.ndarray]:
    """The field whose zero level is the tissue's surface (skin outside, bone inside) and the
    envelope: in the skin, not bone, not behind bone seen from the front, within ``depth_mm``
    of the skin."""
    v = values.astype(np.float32)
    k = max(1, int(np.ceil(rules.tooth_gap_mm / 2 / spacing[2])))
    line = np.ones((1, 1, 2 * k + 1), dtype=bool)
    sealed = ndi.binary_closing(np.pad(bone, [(0, 0), (0, 0), (k, k)]), structure=line)[:, :, k:-k] | bone
    behind = np.logical_or.accumulate(sealed[:, ::-1], axis=1)[:, ::-1]
    depth = ndi.distance_transform_edt(skin, sampling=spacing)
    envelope = anatomy.largest(skin & ~bone & ~behind & (depth <= rules.depth_mm))
    g = np.minimum(v - rules.skin, rules.bone - v)
    g = np.where(skin & (v < rules.skin), 0.5 * (rules.bone - rules.skin), g)  # air inside counts as tissue
    return np.where(envelope, g, -np.abs(g) - 1e-3), envelope


def _cut(surface, cuts: dict[str, float]):
    """The closed surface cut by the planes of the face's frame, each capped flat."""
    slope = np.tan(np.radians(cuts["inferior_cut_slope_deg"]))
    planes = [((0.0, 0.0, cuts["superior_cut_z_mm"]), (0.0, 0.0, -1.0)),
              ((0.0, cuts["posterior_cut_y_mm"], 0.0), (0.0, 1.0, 0.0)),
              ((0.0, cuts["inferior_cut_at_y_mm"], cuts["inferior_cut_z_mm"]), (0.0, -slope, 1.0))]
    for origin, normal in planes:  # keeps the side the normal points to
        surface = surface.clip_closed_surface(normal=normal, origin=origin)
    return _pieces(surface.triangulate().clean(), 1.0)


def _tissue_surface(surface) -> tuple[Mesh, dict]:
    """The cut surface as a closed, outward ``tri3`` Mesh (:func:`~toolkit.mesh.surface.closed_surface`)."""

    mesh, repair = closed_surface(np.asarray(surface.points, dtype=float),
                                  np.asarray(surface.faces.reshape(-1, 4)[:, 1:], dtype=np.int64),
                                  name="tissue surface from the CT")
    x = mesh.points[mesh.cells["tri3"]]
    if np.einsum("ij,ij->i", x[:, 0], np.cross(x[:, 1], x[:, 2])).sum() < 0:
        mesh = Mesh(mesh.points, {"tri3": mesh.cells["tri3"][:, [0, 2, 1]]})
    return mesh, {k: v for k, v in repair.to_dict().items() if v}


# ---------------------------------------------------------------------------------- the pipeline


def _cuts(masks: dict[str, np.ndarray], F: np.ndarray, rules: CTRules) -> tuple[dict, dict]:
    """Condyles, menton, the mandibular plane and the truncation planes, in the face's frame ``F`` (voxel
    centres, mm)."""
    condyles = {}
    for side in ("left", "right"):
        p = F[masks[f"proximal_{side}"]]
        condyles[side] = p[p[:, 2] >= p[:, 2].max() - rules.condyle_band_mm].mean(axis=0)
    distal = F[masks["distal"]]
    central = distal[np.abs(distal[:, 0]) < 8.0]
    central = central if len(central) else distal
    menton = central[np.argmin(central[:, 2])]
    # the mandibular plane: from the menton, the line in the sagittal plane tangent to the lower
    # border of the rami (the proximal segments): the flattest one below all their points
    rami = F[masks["proximal_left"] | masks["proximal_right"]]
    rami = rami[rami[:, 1] < menton[1] - 10.0]
    ratio = (rami[:, 2] - menton[2]) / (rami[:, 1] - menton[1])
    slope = float(ratio.max())  # dz/dy
    touch = rami[np.argmax(ratio)]
    cuts = {"superior_cut_z_mm": float(F[masks["lefort"]][:, 2].max()) + rules.superior_mm,
            "posterior_cut_y_mm": 0.5 * float(condyles["left"][1] + condyles["right"][1]) + rules.posterior_mm,
            "inferior_cut_z_mm": float(menton[2]) - rules.inferior_mm, "inferior_cut_at_y_mm": float(menton[1]),
            "inferior_cut_slope_deg": float(np.degrees(np.arctan(slope)))}
    return {"menton": menton, "ramus_lower_border": touch, "condyle_left": condyles["left"],
            "condyle_right": condyles["right"]}, cuts


def _chin(tissue: Mesh) -> np.ndarray | None:
    p = tissue.points[(np.abs(tissue.points[:, 0]) < 5.0) & (tissue.points[:, 2] < 0)]
    return p[np.argmax(p[:, 1] - p[:, 2])] if len(p) else None


def _affine(volume: Volume, axis: np.ndarray, sign: np.ndarray, spacing: np.ndarray, frame: Frame) -> np.ndarray:
    """(4, 4): the file's voxel index (i, j, k, 1) -> the face's frame (mm)."""
    m = np.zeros((3, 3))
    m[range(3), axis] = sign * spacing
    flip = np.where(sign < 0, (np.asarray(volume.shape)[axis] - 1) * spacing, 0.0)
    out = np.eye(4)
    out[:3, :3] = frame.axes @ m
    out[:3, 3] = frame.axes @ (flip - frame.origin)
    return out


def _check_axes(tissue: Mesh, bones: dict[str, Mesh]) -> None:
    """The surfaces found must be a face in the toolkit's axes (:mod:`toolkit.common.meshes.axes`)."""

    try:
        check_anatomical_axes(tissue.points, {k: b.points for k, b in bones.items()}, source="the CT's surfaces")
    except AxesError as exc:
        raise CTError(f"{exc}. The axes found from the anatomy are wrong for this volume: give them (axes='LPI', "
                      "command line: --axes LPI)") from None


def ct_surfaces(volume, rules: CTRules | None = None) -> CTSurfaces:
    """The face's surfaces from a head CT (rules in the module docstring).

    Parameters
    ----------
    volume : a :class:`~toolkit.mesh.volume.Volume` or an NRRD file (``.nrrd``, ``.nhdr``)
    rules : :class:`~toolkit.mesh.ct_anatomy.CTRules` (thresholds, axes, plane distances); None:
        the defaults (headsq's thresholds: skin 500, bone 1150)

    Returns
    -------
    :class:`CTSurfaces`: the tissue's closed ``tri3`` surface and the five bone surfaces, mm, in the
    face's frame, and a report of what was found.

    Raises
    ------
    VolumeError for a file or thresholds that cannot be a head CT (before any segmentation),
    CTError for anatomy that cannot be found (naming the rule's option that sets it by hand).
    """
    rules = rules or CTRules()
    volume = volume if isinstance(volume, Volume) else read_volume(volume)
    volume.check(skin=rules.skin, bone=rules.bone)
    times = {}

    t0 = time.perf_counter()
    axis, sign, axes = anatomy.orientation(volume.values, volume.spacing, volume.handedness, rules)
    values, spacing = anatomy.reoriented(volume.values, volume.spacing, axis, sign)
    skin = anatomy.skin_mask(values, spacing, rules)
    bone = anatomy.bone_mask(values, skin, rules)
    times["axes_and_masks"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    marks = anatomy.landmarks(values, spacing, skin, bone, rules)
    centres = np.indices(values.shape).transpose(1, 2, 3, 0) * spacing
    X, F = marks.occlusal(centres), marks.face(centres)
    masks, planes = anatomy.osteotomy(values, bone, marks.teeth, X, marks.midline_mm / spacing[0], rules)
    found, cuts = _cuts(masks, F, rules)
    times["landmarks_and_segments"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    near = (F[..., 2] < cuts["superior_cut_z_mm"] + 15.0) & (F[..., 1] > cuts["posterior_cut_y_mm"] - 15.0) \
        & (F[..., 2] > cuts["inferior_cut_z_mm"] - 15.0)
    masks["skull"] = masks["skull"] & near  # the skull near the tissue: the cranium carries nothing
    if not masks["skull"].any():
        raise CTError("no skull within 15 mm of the tissue's cuts; expected the skull above the Le Fort I plane "
                      "(check lefort_mm and superior_mm)")
    bones = {name: _bone_surface(values, masks[name], spacing, marks.face, rules) for name in SEGMENT_NAMES}
    times["bone_surfaces"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    skin, lips = anatomy.closed_lips(skin, bone, X, spacing, rules, planes["last_upper_molar_y_mm"])
    g, envelope = _tissue_field(values, skin, bone, spacing, rules)
    tissue, repair = _tissue_surface(_cut(_pieces(_contour(g, 0.0, spacing, marks.face), 1.0), cuts))
    _check_axes(tissue, bones)
    times["tissue_surface"] = time.perf_counter() - t0

    def mm(p):
        return None if p is None else [round(float(c), 2) for c in p]

    report = {
        "volume": {"source": volume.source, "shape": list(volume.shape), "spacing_mm": volume.spacing.tolist(),
                   "space": volume.space},
        "thresholds": {"skin": rules.skin, "bone": rules.bone, "teeth": round(marks.teeth_threshold, 1)},
        "axes": axes,
        "index_to_mm": np.round(_affine(volume, axis, sign, spacing, marks.face), 6).tolist(),
        "landmarks_mm": {"nose_tip": mm(marks.face(marks.nose)), "chin": mm(_chin(tissue)), "incisal_point": [0.0] * 3,
                         **{k: mm(v) for k, v in found.items()}},
        "occlusal_plane": {"pitch_deg": round(marks.pitch_deg, 2), "tilt_in_frame_deg": rules.occlusal_tilt_deg,
                           "tooth_gap_mm": round(marks.gap_mm, 2), "teeth_voxels": int(marks.teeth.sum()),
                           "found": rules.occlusal_pitch_deg is None},
        "osteotomy_mm": {k: round(float(v), 2) for k, v in planes.items()},
        "cuts_mm": {k: round(float(v), 2) for k, v in cuts.items()},
        "mouth": {"status": "closed: no commissures, no lip sliding (toolkit mesh --commissures cuts the lips)",
                  "lips_closed": lips},
        "surfaces": {"tissue": {"points": int(tissue.n_points), "triangles": int(len(tissue.cells["tri3"])),
                                "bounds_mm": np.round(tissue.bounds, 1).tolist()},
                     **{k: {"points": int(b.n_points), "triangles": int(len(b.cells["tri3"]))}
                        for k, b in bones.items()}},
        "tissue_repair": repair,
        "voxels": {k: int(v.sum()) for k, v in masks.items()} | {"tissue_envelope": int(envelope.sum())},
        "rules": rules.to_dict(),
        "seconds": {k: round(v, 3) for k, v in times.items()},
    }
    return CTSurfaces(tissue, bones, None, report)
