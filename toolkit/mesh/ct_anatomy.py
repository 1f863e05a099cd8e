"""Where things are in a head CT: its anatomical axes, skin, bone and teeth, the occlusal plane,
and the bony segments of a virtual osteotomy.

The rules and the anatomy behind each are stated in :mod:`toolkit.mesh.ct`; :class:`CTRules`
holds their values. Everything here works on voxel masks (numpy, ``scipy.ndimage``); the
surfaces are made in :mod:`toolkit.mesh.ct`.

Arrays are indexed ``[x, y, z]`` once reoriented (:func:`reoriented`): x toward the patient's
left, y anterior, z superior, voxel centres at ``index * spacing`` mm.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from toolkit.mesh.ct_rules import CTError, CTRules, axes_code, axes_text

__all__ = ["CTError", "CTRules", "Frame", "Landmarks", "orientation", "reoriented", "skin_mask", "bone_mask",
           "landmarks", "osteotomy", "closed_lips"]

# ----------------------------------------------------------------------------------------- axes


def largest(mask: np.ndarray) -> np.ndarray:
    """The largest connected piece of ``mask`` (face connectivity)."""
    lab, n = ndi.label(mask)
    if n == 0:
        return mask
    return lab == np.argmax(np.bincount(lab.ravel())[1:]) + 1


def _last_true(s: np.ndarray) -> np.ndarray:
    """Index of the last True along axis 0, ``s.shape[1:]`` (0 where none)."""
    return s.shape[0] - 1 - np.argmax(s[::-1], axis=0)


def _protrusion(skin: np.ndarray, along: int, sign: float, spacing: np.ndarray, width_mm: float = 20.0) -> np.ndarray:
    """Per lateral column and slice ``(n_lateral, n_slices)``, how far the head's outline stands
    out along ``sign`` x index axis ``along`` (0 or 1) beyond its outline ``width_mm`` to either
    side, mm: large at the nose."""
    s = skin if along == 0 else skin.transpose(1, 0, 2)
    if sign < 0:
        s = s[::-1]
    has = s.any(axis=0)
    low = -1e9
    front = np.where(has, _last_true(s) * spacing[along], low)
    w = max(1, int(round(width_mm / spacing[1 - along])))
    pad = np.full((w, front.shape[1]), low)
    padded = np.vstack([pad, front, pad])
    side = np.maximum(padded[:-2 * w], padded[2 * w:])
    return np.where(has, front - np.maximum(side, front - 100.0), 0.0)


def _middle_third(skin: np.ndarray) -> slice:
    ks = np.flatnonzero(skin.any(axis=(0, 1)))
    third = (ks[-1] - ks[0]) // 3
    return slice(ks[0] + third, ks[-1] - third + 1)


def _superior_sign(skin: np.ndarray, bone: np.ndarray) -> tuple[float, dict]:
    """+1 if the cranium lies toward the last slice: the share of the head inside the bone's
    filled outline, slice by slice, over the fifth of the head at each end."""
    plane = np.zeros((3, 3, 3), dtype=bool)
    plane[:, :, 1] = ndi.generate_binary_structure(2, 1)
    inside = ndi.binary_fill_holes(bone, structure=plane).sum(axis=(0, 1))
    area = skin.sum(axis=(0, 1))
    ks = np.flatnonzero(area)
    lo, hi = ks[0], ks[-1]
    m = max(1, (hi - lo + 1) // 5)
    first = inside[lo:lo + m].sum() / max(area[lo:lo + m].sum(), 1)
    last = inside[hi - m + 1:hi + 1].sum() / max(area[hi - m + 1:hi + 1].sum(), 1)
    evidence = {"enclosed_share_first_slices": round(float(first), 3),
                "enclosed_share_last_slices": round(float(last), 3)}
    if max(first, last) < 0.1 or max(first, last) < 2 * min(first, last):
        raise CTError(f"cannot tell the cranium's end of the slice axis: the bone encloses {first:.0%} of the head in "
                      f"the first fifth of the slices and {last:.0%} in the last; expected a cranium (the brain inside "
                      "the skull) at one end, twice the other's. Give the axes (axes='LPI', command line: --axes LPI)")
    return (1.0 if last > first else -1.0), evidence


def orientation(values: np.ndarray, spacing: np.ndarray, handedness: str | None,
                rules: CTRules) -> tuple[np.ndarray, np.ndarray, dict]:
    """For toolkit x, y, z: the index axis along it ``(3,)`` and its sign ``(3,)``, and the evidence.

    values : (n0, n1, n2) the volume as read; spacing : (3,) mm
    handedness : ``"left"``/``"right"`` from the header, or None (taken as right-handed)
    """
    if rules.axes is not None:
        axis, sign = axes_code(rules.axes)
        return axis, sign, {"axes": axes_text(axis, sign), "how": "given (axes=)"}
    skin = largest(values >= rules.skin)
    sup, evidence = _superior_sign(skin, (values >= rules.bone) & skin)
    band = skin[:, :, _middle_third(skin)]
    score = {(a, s): float(_protrusion(band, a, s, spacing).max()) for a in (0, 1) for s in (1.0, -1.0)}
    diff = {a: score[(a, 1.0)] - score[(a, -1.0)] for a in (0, 1)}
    ap = max((0, 1), key=lambda a: abs(diff[a]))
    evidence["protrusion_mm"] = {f"axis{a}{'+' if s > 0 else '-'}": round(v, 1) for (a, s), v in score.items()}
    if abs(diff[ap]) < 5.0 or abs(diff[ap]) < abs(diff[1 - ap]) + 3.0:
        raise CTError(f"cannot tell the face's front: the head's outline protrudes {evidence['protrusion_mm']} mm "
                      "along the in-plane index axes (+/-); expected the nose, 5 mm or more beyond the opposite side, "
                      "along one axis only. Give the axes (axes='LPI', command line: --axes LPI)")
    axis = np.array([1 - ap, ap, 2])
    sign = np.array([1.0, 1.0 if diff[ap] > 0 else -1.0, sup])
    # the patient's (left, anterior, superior) is a left-handed triad: a right-handed index frame
    # maps onto it with a negative determinant
    m = np.zeros((3, 3))
    m[range(3), axis] = sign
    handed = handedness or "right"
    if np.sign(np.linalg.det(m)) != (-1.0 if handed == "right" else 1.0):
        sign[0] = -1.0
    source = "the header" if handedness else "not in the header: taken as the DICOM and NIfTI frames are"
    evidence.update(axes=axes_text(axis, sign),
                    how=f"found from the anatomy; left-right from a {handed}-handed index frame ({source})")
    return axis, sign, evidence


def reoriented(values: np.ndarray, spacing: np.ndarray, axis: np.ndarray, sign: np.ndarray):
    """The array with its axes along toolkit x, y, z, increasing toward the left, anterior and
    superior, and its spacing ``(3,)`` mm."""
    a = np.transpose(values, axis)
    a = a[tuple(slice(None, None, -1) if s < 0 else slice(None) for s in sign)]
    return np.ascontiguousarray(a), np.asarray(spacing, dtype=float)[axis]


# ---------------------------------------------------------------------------------------- masks


def ellipsoid(radius) -> np.ndarray:
    """A boolean ellipsoid of the given radii in voxels ``(2 r + 1)`` per axis."""
    r = np.asarray(radius)
    g = np.indices(2 * r + 1) - r.reshape(-1, *([1] * r.size))
    return ((g / r.reshape(-1, *([1] * r.size))) ** 2).sum(axis=0) <= 1.0


def filled(mask: np.ndarray) -> np.ndarray:
    """``mask`` with every enclosed cavity filled; the volume's cut ends (first and last slices)
    close the body, as lids."""
    lids = [ndi.binary_fill_holes(mask[:, :, k])[:, :, None] for k in (0, -1)]
    return ndi.binary_fill_holes(np.concatenate([lids[0], mask, lids[1]], axis=2))[:, :, 1:-1]


def skin_mask(values: np.ndarray, spacing: np.ndarray, rules: CTRules) -> np.ndarray:
    """Everything inside the skin: the largest piece above ``skin``, openings narrower than
    ``closing_mm`` closed, cavities filled."""
    skin = largest(values >= rules.skin)
    r = np.maximum(1, np.round(rules.closing_mm / 2 / spacing).astype(int))
    pad = [(ri + 1, ri + 1) for ri in r]
    closed = ndi.binary_closing(np.pad(skin, pad), structure=ellipsoid(r))[tuple(slice(ri + 1, -ri - 1) for ri in r)]
    return filled(closed | skin)


def bone_mask(values: np.ndarray, skin: np.ndarray, rules: CTRules) -> np.ndarray:
    """Bone inside the skin: the pieces above ``bone`` of at least ``min_bone_piece`` of the
    largest."""
    lab, n = ndi.label((values >= rules.bone) & skin)
    if n == 0:
        raise CTError(f"no voxel inside the skin reaches the bone threshold {rules.bone:g}; expected the skeleton "
                      "above it (bone=, command line: --bone)")
    sizes = np.bincount(lab.ravel())
    sizes[0] = 0
    return (sizes >= rules.min_bone_piece * sizes.max())[lab]


def closed_lips(skin: np.ndarray, bone: np.ndarray, X: np.ndarray, spacing: np.ndarray, rules: CTRules,
                y_back: float) -> tuple[np.ndarray, dict]:
    """The skin with the mouth closed. In front of the last molars (``y_back``, occlusal frame),
    within 20 mm of the occlusal plane and 40 mm of the midline: the air that a disc of diameter
    ``lip_gap_mm`` in the sagittal plane cannot enter (between the lips, and between the lips and
    the incisors), and the air within two voxels of a tooth bare to the air (parted lips show the
    incisal edges; the model's lips cover them). Returns the filled skin and what was closed."""
    r = np.maximum(1, np.round(rules.lip_gap_mm / 2 / spacing).astype(int))
    disc = ellipsoid(r)[r[0]:r[0] + 1]
    pad = [(0, 0), (r[1], r[1]), (r[2], r[2])]
    closed = ndi.binary_closing(np.pad(skin, pad), structure=disc)[:, r[1]:-r[1], r[2]:-r[2]]
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    mouth = (np.abs(x) < 40.0) & (np.abs(z) < 20.0) & (y > y_back)
    gap = closed & ~skin & mouth
    air = ~(skin | gap)
    cube = np.ones((3, 3, 3), dtype=bool)
    bare = bone & mouth & ndi.binary_dilation(air, structure=cube)
    cover = ndi.binary_dilation(bare, structure=cube, iterations=2) & air & mouth
    closed_voxels = gap | cover
    out = {"air_voxels_closed": int(closed_voxels.sum()), "bare_tooth_voxels": int(bare.sum())}
    if closed_voxels.any():
        out["x_mm"] = [round(float(x[closed_voxels].min()), 1), round(float(x[closed_voxels].max()), 1)]
    return filled(skin | closed_voxels), out


# ------------------------------------------------------------------------------------ landmarks


@dataclass(frozen=True)
class Frame:
    """A frame of the face: ``X = (p - origin) @ axes.T`` (rows of ``axes``: x, y, z), p in the
    reoriented volume (index x spacing), mm."""

    origin: np.ndarray
    axes: np.ndarray

    def __call__(self, p) -> np.ndarray:
        return (np.asarray(p, dtype=float) - self.origin) @ self.axes.T

    def shifted(self, index_offset, spacing) -> Frame:
        """The same frame for a sub-array starting at ``index_offset``."""
        return Frame(self.origin - np.asarray(index_offset) * spacing, self.axes)


@dataclass(frozen=True)
class Landmarks:
    """What :func:`landmarks` finds (reoriented volume, mm unless said).

    midline_mm : x of the mid-sagittal plane; nose : (3,) the nose tip
    teeth : boolean mask of the tooth voxels; teeth_threshold : CT value
    pitch_deg : the occlusal plane's tilt about x (anterior end down positive); gap_mm : the
        gap between the rows of teeth it runs through
    occlusal : frame on the occlusal plane (z its normal, origin the incisal point)
    face : the face's frame (the occlusal frame turned so that the plane is inclined
        ``occlusal_tilt_deg``, anterior end down)
    """

    midline_mm: float
    nose: np.ndarray
    teeth: np.ndarray
    teeth_threshold: float
    pitch_deg: float
    gap_mm: float
    occlusal: Frame
    face: Frame


def _midline_and_nose(skin: np.ndarray, spacing: np.ndarray) -> tuple[float, np.ndarray]:
    """x of the mid-sagittal plane (median over the middle third of the slices of the middle of
    the skin's width) and the nose tip (the most protruding front point of that band), mm."""
    band_slices = _middle_third(skin)
    band = skin[:, :, band_slices]
    has = band.any(axis=1)  # (x, k)
    lo = np.argmax(has, axis=0)
    hi = has.shape[0] - 1 - np.argmax(has[::-1], axis=0)
    mid = float(np.median(0.5 * (lo + hi)[has.any(axis=0)])) * spacing[0]
    prot = _protrusion(band, 1, 1.0, spacing)
    xi, kk = np.unravel_index(np.argmax(prot), prot.shape)
    yi = _last_true(band.transpose(1, 0, 2))[xi, kk]
    return mid, np.array([xi, yi, band_slices.start + kk]) * spacing


def _occlusal_plane(teeth: np.ndarray, rules: CTRules) -> tuple[float, float, float]:
    """(pitch rad, offset mm, gap mm): of the planes with normal (0, sin pitch, cos pitch), the
    one through the widest gap between the teeth's projections (between their 15th and 85th
    percentiles); teeth ``(k, 3)`` mm."""
    pitches = np.radians(np.arange(-45.0, 45.5, 1.0) if rules.occlusal_pitch_deg is None
                         else [rules.occlusal_pitch_deg])
    n = np.stack([np.zeros_like(pitches), np.sin(pitches), np.cos(pitches)], axis=1)
    s = np.sort(teeth @ n.T, axis=0)  # (k, pitches)
    k0, k1 = int(0.15 * len(s)), int(0.85 * len(s)) + 1
    gaps = np.diff(s[k0:k1], axis=0)
    at = np.argmax(gaps, axis=0)
    best = int(np.argmax(gaps[at, np.arange(len(pitches))]))
    i = at[best]
    offset = 0.5 * (s[k0 + i, best] + s[k0 + i + 1, best]) + rules.occlusal_shift_mm
    return float(pitches[best]), float(offset), float(gaps[i, best])


def _rotation(pitch: float) -> np.ndarray:
    """Rows x, y, z of a frame turned by ``pitch`` about x (anterior end of y down)."""
    return np.array([[1.0, 0.0, 0.0], [0.0, np.cos(pitch), -np.sin(pitch)], [0.0, np.sin(pitch), np.cos(pitch)]])


def landmarks(values: np.ndarray, spacing: np.ndarray, skin: np.ndarray, bone: np.ndarray,
              rules: CTRules) -> Landmarks:
    """The midline, nose tip, teeth, occlusal plane and the frames of the face (see
    :mod:`toolkit.mesh.ct`)."""
    mid, nose = _midline_and_nose(skin, spacing)
    air = float(np.percentile(values, 1.0))
    threshold = float(rules.teeth) if rules.teeth is not None else air + 2.4 * (rules.bone - air)
    idx = np.indices(values.shape)
    near = ((np.abs(idx[0] * spacing[0] - mid) < 35.0) & (idx[1] * spacing[1] > nose[1] - 80.0)
            & (idx[2] * spacing[2] < nose[2] - 5.0))
    teeth = near & bone & (values >= threshold)
    points = np.argwhere(teeth) * spacing
    if len(points) < 10:
        raise CTError(f"{len(points)} voxels at or above the teeth threshold {threshold:g} within 35 mm of the midline "
                      "and 80 mm behind the nose tip; expected the teeth. Give the teeth threshold (teeth=, command "
                      "line: --teeth) or check the bone threshold")
    pitch, offset, gap = _occlusal_plane(points, rules)
    rot = _rotation(pitch)
    forward, normal = rot[1], rot[2]
    on_plane = points[np.abs(points @ normal - offset) < 8.0]
    central = on_plane[np.abs(on_plane[:, 0] - mid) < 10.0]
    front = central if len(central) else on_plane
    incisal = front[np.argmax(front @ forward)]
    origin = np.array([mid, 0.0, 0.0]) + forward * (incisal @ forward) + normal * offset
    occlusal = Frame(origin, rot)
    face = Frame(origin, _rotation(pitch - np.radians(rules.occlusal_tilt_deg)))
    return Landmarks(mid, nose, teeth, threshold, float(np.degrees(pitch)), gap, occlusal, face)


# ------------------------------------------------------------------------------------ osteotomy


def _watershed(values: np.ndarray, bone: np.ndarray, seeds: list[np.ndarray]) -> np.ndarray:
    """Label of each bone voxel (1 + index of its seed) by a watershed on the CT values flooded
    from the seeds, densest voxels first; 0 off the bone."""
    v = values.astype(np.float64)
    hi = float(np.percentile(v[bone], 99.5))
    lo = float(v[bone].min())
    cost = np.clip((hi - v) / max(hi - lo, 1e-9) * 60000.0, 0, 60000).astype(np.uint16)
    cost[~bone] = 65535
    markers = np.zeros(values.shape, dtype=np.int16)
    markers[~bone] = len(seeds) + 1
    for k, seed in enumerate(seeds):
        markers[seed & bone] = k + 1
    labels = ndi.watershed_ift(cost, markers)
    labels[~bone] = 0
    return labels


def _touching(mask: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The connected pieces of ``mask`` holding a voxel of ``seed``."""
    lab, _ = ndi.label(mask)
    hit = np.unique(lab[seed & mask])
    return np.isin(lab, hit[hit > 0])


def _mirrored(mask: np.ndarray, mid_index: float) -> np.ndarray:
    """``mask`` mirrored across x = ``mid_index`` (voxels along axis 0)."""
    k = int(round(2 * mid_index))
    i = np.arange(mask.shape[0])
    ok = (k - i >= 0) & (k - i < mask.shape[0])
    out = np.zeros_like(mask)
    out[i[ok]] = mask[k - i[ok]]
    return out


def osteotomy(values: np.ndarray, bone: np.ndarray, teeth: np.ndarray, X: np.ndarray, mid_index: float,
              rules: CTRules) -> tuple[dict[str, np.ndarray], dict]:
    """Masks of the segments ``lefort``, ``distal``, ``proximal_left``, ``proximal_right`` and
    ``skull``, and the planes that cut them (``X``: voxel centres in the occlusal frame
    ``(n0, n1, n2, 3)`` mm)."""
    x, y, z = X[..., 0], X[..., 1], X[..., 2]
    upper, lower = teeth & (z > 0), teeth & (z < 0)
    if upper.sum() < 3 or lower.sum() < 3:
        raise CTError(f"{int(upper.sum())} tooth voxels above the occlusal plane and {int(lower.sum())} below; "
                      "expected both rows of teeth. Check the teeth threshold (teeth=, command line: --teeth) or give "
                      "the occlusal plane's tilt (occlusal_pitch_deg=, command line: --occlusal-pitch)")
    last_upper = float(y[upper].min())
    tuberosity = last_upper - rules.tuberosity_mm
    split = {}
    for side, sel in (("left", x > 0), ("right", x <= 0)):
        ys = y[lower & sel]
        if ys.size == 0:
            raise CTError(f"no lower tooth on the {side}; expected teeth on both sides to place the sagittal splits")
        split[side] = float(ys.min()) - rules.split_mm
    front_of_split = np.where(x > 0, y > split["left"], y > split["right"])
    half = float(np.abs(x[teeth]).max())
    seeds = [
        largest(bone & (z < -12.0) & front_of_split),                                            # mandible's body
        largest(bone & (z > 8.0) & (z < rules.lefort_mm) & (y > tuberosity) & (np.abs(x) < half)),  # maxilla
        bone & ((np.arange(bone.shape[2]) >= 0.9 * bone.shape[2])[None, None, :]                 # cranium
                | (z > rules.lefort_mm + 15.0)
                | ((np.abs(x) < 15.0) & (y < tuberosity - 25.0) & (z < -10.0))),                 # spine, clivus
    ]
    if not seeds[0].any() or not seeds[1].any():
        raise CTError("no bone 12 mm below the lower teeth or 8 mm above the upper teeth to start the jaws from; "
                      "expected a mandible and a maxilla around the occlusal plane (check occlusal_pitch_deg)")
    labels = _watershed(values, bone, seeds)
    mandible = _touching(labels == 1, seeds[0])
    # the rami are mirror images: a condyle the watershed gave to the skull (a thin condylar neck
    # floods after the joint space) is taken back from the other side's
    mandible = _touching(mandible | (_mirrored(mandible, mid_index) & bone & ~front_of_split), seeds[0])
    rest = bone & ~mandible
    lefort = _touching(rest & (z < rules.lefort_mm) & (y > tuberosity), seeds[1])
    distal = _touching(mandible & (z < 0) & front_of_split, seeds[0])
    joined = ndi.binary_dilation(distal, structure=np.ones((3, 3, 3), dtype=bool))
    proximal = {side: _touching(mandible & ~distal & sel, joined) for side, sel in (("left", x > 0),
                                                                                     ("right", x <= 0))}
    loose = mandible & ~distal & ~proximal["left"] & ~proximal["right"]
    masks = {"lefort": lefort, "distal": distal, "proximal_left": proximal["left"],
             "proximal_right": proximal["right"], "skull": (rest & ~lefort) | loose}
    planes = {"le_fort_i_above_occlusal_mm": rules.lefort_mm, "tuberosity_y_mm": tuberosity,
              "split_left_y_mm": split["left"], "split_right_y_mm": split["right"],
              "last_upper_molar_y_mm": last_upper}
    empty = [k for k, v in masks.items() if not v.any()]
    if empty:
        raise CTError(f"segments {empty} are empty (planes in the occlusal frame: "
                      f"{ {k: round(v, 1) for k, v in planes.items()} }); expected bone in each. Check lefort_mm, "
                      "split_mm and tuberosity_mm")
    return masks, planes
