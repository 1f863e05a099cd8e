"""A CT volume read from an NRRD file: its values, voxel spacing and what its header says about
its axes.

:func:`read_volume` reads the NRRD format (https://teem.sourceforge.net/nrrd/format.html) as CT
exports and 3D Slicer write it: a header attached to the data (``.nrrd``) or detached from it
(``.nhdr`` naming one data file, a numbered series such as ``quarter.%d 1 93 1``, or a ``LIST``
of files), raw or gzip encoding, integer or floating-point samples of either byte order.
:meth:`Volume.check` refuses a volume that is not a head CT's size in mm before anything heavy
is computed.

The header's ``space`` (``3D-left-handed``, ``left-posterior-superior``, ...) and ``space
directions`` are kept as read: a header that names only a handedness leaves the anatomical
directions to be found from the anatomy (:mod:`toolkit.mesh.ct`).
"""

from __future__ import annotations

import gzip
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from toolkit.common.errors import ToolkitError

__all__ = ["Volume", "VolumeError", "read_volume"]

#: NRRD sample types -> numpy dtype kinds (byte order added from ``endian``)
_TYPES = {
    **dict.fromkeys(["signed char", "int8", "int8_t"], "i1"),
    **dict.fromkeys(["uchar", "unsigned char", "uint8", "uint8_t"], "u1"),
    **dict.fromkeys(["short", "short int", "signed short", "signed short int", "int16", "int16_t"], "i2"),
    **dict.fromkeys(["ushort", "unsigned short", "unsigned short int", "uint16", "uint16_t"], "u2"),
    **dict.fromkeys(["int", "signed int", "int32", "int32_t"], "i4"),
    **dict.fromkeys(["uint", "unsigned int", "uint32", "uint32_t"], "u4"),
    **dict.fromkeys(["float"], "f4"),
    **dict.fromkeys(["double"], "f8"),
}
#: largest voxel edge (mm) and field of view (mm) of a head CT; anything outside is another unit or not a CT
_PLAUSIBLE_SPACING_MM = (0.05, 10.0)
_PLAUSIBLE_FIELD_MM = (60.0, 1000.0)


class VolumeError(ToolkitError, ValueError):
    """A volume file that cannot be read, or values that cannot be a head CT."""


@dataclass(frozen=True)
class Volume:
    """A 3D image on a regular grid.

    values : (n0, n1, n2) array, scanner units (the file's sample type); index 0 varies fastest in
        the file
    spacing : (3,) float, mm, voxel edge along each index axis
    space : the header's ``space`` field (``""`` when absent), e.g. ``3D-left-handed``
    directions : (3, 3) float or None, the header's ``space directions`` (row i: index axis i), mm
    source : the file read
    """

    values: np.ndarray
    spacing: np.ndarray
    space: str = ""
    directions: np.ndarray | None = None
    source: str = ""
    header: dict = field(default_factory=dict)

    def __post_init__(self):
        values = np.asarray(self.values)
        spacing = np.asarray(self.spacing, dtype=float).reshape(-1)
        if values.ndim != 3:
            raise VolumeError(f"{self.source or 'volume'}: {values.ndim} dimensions (shape {values.shape}); expected a "
                              "3D image (a CT series as one volume)")
        if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or np.any(spacing <= 0):
            raise VolumeError(f"{self.source or 'volume'}: voxel spacing {spacing.tolist()}; expected three positive "
                              "lengths in mm (NRRD 'spacings' or 'space directions')")
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "spacing", spacing)

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.values.shape)

    @property
    def extent_mm(self) -> np.ndarray:
        """(3,) float, mm: the field of view along each index axis."""
        return np.asarray(self.shape) * self.spacing

    @property
    def handedness(self) -> str | None:
        """``"left"`` or ``"right"`` when the header says how the index axes turn (``space`` names a
        handedness or a patient space, or ``space directions`` are given), else None."""
        if self.directions is not None and np.all(np.isfinite(self.directions)):
            det = float(np.linalg.det(self.directions))
            if det != 0.0:
                # a patient space (LPS, RAS) is right-handed: the index frame turns as its directions do
                return "right" if det > 0 else "left"
        text = self.space.lower()
        if "left-handed" in text:
            return "left"
        if "right-handed" in text:
            return "right"
        return None

    def check(self, *, skin: float, bone: float) -> Volume:
        """Refuse a volume that cannot be a head CT in mm, or thresholds that select nothing or
        everything; returns the volume. Cheap: run before any segmentation."""
        lo, hi = _PLAUSIBLE_SPACING_MM
        name = self.source or "volume"
        if self.spacing.max() > hi or self.spacing.min() < lo:
            raise VolumeError(f"{name}: voxel spacing {self.spacing.round(4).tolist()} mm; expected {lo}-{hi} mm "
                              "(a spacing in m or cm? the header's 'spacings' must be in mm)")
        flo, fhi = _PLAUSIBLE_FIELD_MM
        field_mm = self.extent_mm
        if field_mm.max() < flo or field_mm.max() > fhi:
            raise VolumeError(f"{name}: field of view {field_mm.round(1).tolist()} mm; expected a head of {flo:g}-"
                              f"{fhi:g} mm (check the spacing's unit)")
        if min(self.shape) < 8:
            raise VolumeError(f"{name}: shape {list(self.shape)}; expected at least 8 voxels along each axis")
        if not bone > skin:
            raise VolumeError(f"bone threshold {bone:g} is not above the skin threshold {skin:g}; expected skin < "
                              "bone in the volume's units (e.g. skin 500, bone 1150 for headsq; -300 and 300 in HU)")
        vmin, vmax = float(self.values.min()), float(self.values.max())
        head = float(np.mean(self.values >= skin))
        if not 0.01 <= head <= 0.95:
            raise VolumeError(f"skin threshold {skin:g} selects {100 * head:.1f} % of the voxels (values "
                              f"{vmin:g} to {vmax:g}); expected a head within the field, 1-95 %: choose a value "
                              "between the air's and the soft tissue's (skin)")
        hard = float(np.mean(self.values >= bone))
        if not 1e-3 <= hard <= 0.5 * head:
            raise VolumeError(f"bone threshold {bone:g} selects {100 * hard:.2f} % of the voxels ({100 * head:.1f} % "
                              f"above the skin threshold; values {vmin:g} to {vmax:g}); expected the skeleton, 0.1 % "
                              "to half the head: choose a value between the soft tissue's and the bone's (bone)")
        return self


def _header(text: str, path: Path) -> dict:
    lines = text.splitlines()
    if not lines or not re.fullmatch(r"NRRD000[1-5]", lines[0].strip()):
        first = lines[0][:40] if lines else ""
        raise VolumeError(f"{str(path)!r} starts with {first!r}; expected an NRRD header ('NRRD0004' on the first "
                          "line: .nrrd or .nhdr)")
    fields = {}
    for line in lines[1:]:
        if not line.strip() or line.startswith("#"):
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise VolumeError(f"{str(path)!r}: header line {line!r} has no 'field: value'")
        fields[key.strip().lower()] = value.lstrip("=").strip()
    return fields


def _floats(text: str) -> list[float]:
    return [float(v) for v in re.findall(r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?|nan", text)]


def _directions(text: str) -> np.ndarray | None:
    vectors = re.findall(r"\(([^)]*)\)", text)
    if len(vectors) != 3:
        return None
    return np.array([_floats(v) for v in vectors], dtype=float)


def _data_files(spec: str, header_lines: list[str], path: Path) -> list[Path]:
    """The detached data files of ``data file: ...``: one file, a ``%d`` series or a ``LIST``."""
    parts = spec.split()
    if parts and parts[0] == "LIST":
        index = next(i for i, ln in enumerate(header_lines) if ln.lower().startswith("data file"))
        return [path.parent / ln.strip() for ln in header_lines[index + 1:] if ln.strip()]
    if len(parts) >= 4 and "%" in parts[0]:
        first, last, step = (int(v) for v in parts[1:4])
        numbers = range(first, last + (1 if step > 0 else -1), step)
        return [path.parent / (parts[0] % k) for k in numbers]
    return [path.parent / spec]


def read_volume(path) -> Volume:
    """Read a 3D NRRD volume (attached ``.nrrd`` or detached ``.nhdr`` header).

    Parameters
    ----------
    path : the ``.nrrd`` or ``.nhdr`` file

    Returns
    -------
    :class:`Volume`: values ``(n0, n1, n2)`` in the file's sample type (index 0 fastest in the
    file), spacing ``(3,)`` mm from ``spacings`` or the lengths of ``space directions``.

    Raises :class:`VolumeError` naming the file and the field for a header or data it cannot read.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{str(path)!r} does not exist; expected an NRRD volume (.nrrd or .nhdr)")
    raw = path.read_bytes()
    split = raw.find(b"\n\n")
    head = raw if split < 0 else raw[:split]
    try:
        head_text = head.decode("ascii")
    except UnicodeDecodeError:
        raise VolumeError(f"{str(path)!r}: the header is not text; expected an NRRD header ('NRRD0004' ...)") from None
    fields = _header(head_text, path)
    missing = [k for k in ("dimension", "sizes", "type", "encoding") if k not in fields]
    if missing:
        raise VolumeError(f"{str(path)!r}: header lacks {missing}; expected the NRRD fields dimension, sizes, type, "
                          "encoding")
    sizes = [int(v) for v in fields["sizes"].split()]
    if int(fields["dimension"]) != 3 or len(sizes) != 3:
        raise VolumeError(f"{str(path)!r}: dimension {fields['dimension']} (sizes {sizes}); expected a 3D volume")
    kind = _TYPES.get(fields["type"].lower())
    if kind is None:
        raise VolumeError(f"{str(path)!r}: type {fields['type']!r}; expected one of {sorted(set(_TYPES))}")
    order = "<" if fields.get("endian", "little").lower() == "little" else ">"
    dtype = np.dtype(order + kind if kind[1] != "1" else kind)
    encoding = fields["encoding"].lower()
    if encoding not in ("raw", "gzip", "gz"):
        raise VolumeError(f"{str(path)!r}: encoding {encoding!r}; expected raw or gzip")

    if "data file" in fields or "datafile" in fields:
        spec = fields.get("data file", fields.get("datafile"))
        files = _data_files(spec, head_text.splitlines(), path)
        absent = [str(f) for f in files if not f.is_file()]
        if absent:
            raise VolumeError(f"{str(path)!r}: data file {absent[0]!r} does not exist ({len(absent)} of {len(files)} "
                              f"missing; 'data file: {spec}'); expected the data beside the header")
        chunks = [f.read_bytes() for f in files]
    else:
        if split < 0:
            raise VolumeError(f"{str(path)!r}: no blank line after the header and no 'data file'; expected the data "
                              "after the header (.nrrd) or named by 'data file' (.nhdr)")
        chunks = [raw[split + 2:]]
    skip = int(fields.get("byte skip", "0"))
    count = int(np.prod(sizes))
    per_file = count * dtype.itemsize // len(chunks)  # a series splits the data evenly
    data = []
    for chunk in chunks:
        if encoding in ("gzip", "gz"):
            chunk = gzip.decompress(chunk)
        # byte skip -1: the data are the last bytes of the file
        data.append(chunk[skip:] if skip >= 0 else chunk[len(chunk) - per_file:])
    buffer = b"".join(data)
    if len(buffer) != count * dtype.itemsize:
        raise VolumeError(f"{str(path)!r}: {len(buffer)} bytes of data; expected {count * dtype.itemsize} "
                          f"(sizes {sizes} of {fields['type']}): a truncated or missing data file")
    values = np.frombuffer(buffer, dtype=dtype).reshape(sizes[::-1]).transpose(2, 1, 0)
    directions = _directions(fields["space directions"]) if "space directions" in fields else None
    if "spacings" in fields:
        spacing = np.array(_floats(fields["spacings"]), dtype=float)
    elif directions is not None:
        spacing = np.linalg.norm(directions, axis=1)
    else:
        raise VolumeError(f"{str(path)!r}: neither 'spacings' nor 'space directions'; expected the voxel size in mm")
    return Volume(np.ascontiguousarray(values.astype(dtype.newbyteorder("="), copy=False)), spacing,
                  space=fields.get("space", ""), directions=directions, source=str(path), header=fields)
