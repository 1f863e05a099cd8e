"""Mesh files: VTU, XDMF (also time series) and Abaqus ``.inp``, through meshio.

Node and element sets survive every format: Abaqus stores them as ``*NSET`` and
``*ELSET``; VTU and XDMF, which have no sets, carry them as ``uint8`` masks named
``nodeset:NAME`` / ``elset:NAME`` that :func:`read` turns back into sets. Reading a
real mesh with its sets gives the same :class:`~toolkit.common.meshes.mesh.Mesh` the
phantoms give.

Every write is atomic: the file is written under a temporary name in the target
folder and moved into place, so an interrupted run never leaves a half-written
file under the final name.

Units: files are taken to be in mm. A mesh whose extent looks like metres
(largest bounding-box edge < 1) or micrometres (> 5,000) is refused unless
``units=`` says how to convert it.

A file that cannot be read (not text, empty, truncated, a value that is not a number, an
element or set naming a node no ``*NODE`` line defines, a node id defined twice, no volume
cells) raises :class:`~toolkit.common.meshes.mesh.MeshError` naming the file, the line where known,
and what was expected.
"""

from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from io import StringIO
from pathlib import Path

import numpy as np

from toolkit.common.meshes.abaqus import write_abaqus
from toolkit.common.meshes.convert import ELSET_PREFIX, NODESET_PREFIX, from_meshio, to_meshio
from toolkit.common.meshes.mesh import VOLUME_TYPES, Mesh, MeshError, MissingSetError

__all__ = [
    "read",
    "write",
    "write_time_series",
    "read_time_series",
    "TimeSeries",
    "TimeSeriesWriter",
    "check_units",
    "UnitsError",
    "FORMATS",
    "UNIT_SCALES",
    "atomic_path",
    "ensure_room",
]

#: suffix -> meshio format name
FORMATS = {".vtu": "vtu", ".xdmf": "xdmf", ".inp": "abaqus"}
#: factor that converts a length in the given unit to mm
UNIT_SCALES = {"mm": 1.0, "m": 1000.0, "cm": 10.0, "um": 1e-3}
#: plausible largest extent of a head/face/ball model, mm
PLAUSIBLE_EXTENT_MM = (1.0, 5000.0)


class UnitsError(MeshError):
    """A mesh's size suggests another length unit than mm."""


def _format(path: Path) -> str:
    fmt = FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise MeshError(f"unknown mesh format {path.suffix!r} of {str(path)!r}; expected one of {sorted(FORMATS)}")
    return fmt


def check_units(mesh: Mesh, source: str = "mesh") -> None:
    """Raise :class:`UnitsError` if the extent does not look like millimetres."""
    if mesh.n_points == 0:
        return
    ext = float(mesh.extent.max())
    lo, hi = PLAUSIBLE_EXTENT_MM
    if ext < lo:
        raise UnitsError(
            f"{source} is {ext:.4g} units across: that looks like metres, not mm (a face is ~100-200 mm)."
            f" Pass units='m' (command line: --units m) to convert, or check=False if it really is that small."
        )
    if ext > hi:
        raise UnitsError(
            f"{source} is {ext:.4g} units across: that looks like micrometres, not mm (a face is ~100-200 mm)."
            f" Pass units='um' (command line: --units um) to convert."
        )


class atomic_path:
    """Context manager yielding a temporary path that replaces ``path`` on success.

    >>> with atomic_path("out.vtu") as tmp:
    ...     write_somehow(tmp)
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    def __enter__(self) -> Path:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=self.path.suffix, dir=self.path.parent)
        os.close(fd)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the usual file mode
        self.tmp = Path(tmp)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            os.replace(self.tmp, self.path)
        else:
            self.tmp.unlink(missing_ok=True)
        return False


def _encode_sets(mesh: Mesh):
    """meshio mesh with sets as uint8 masks (for VTU/XDMF)."""
    pdata = dict(mesh.point_data)
    cdata = dict(mesh.cell_data)
    for name, ids in mesh.node_sets.items():
        mask = np.zeros(mesh.n_points, dtype=np.uint8)
        mask[ids] = 1
        pdata[NODESET_PREFIX + name] = mask
    for name, ids in mesh.element_sets.items():
        mask = np.zeros(mesh.n_cells, dtype=np.uint8)
        mask[ids] = 1
        cdata[ELSET_PREFIX + name] = mask
    m = Mesh(mesh.points, mesh.cells, point_data=pdata, cell_data=cdata)
    out = to_meshio(m)
    return out


def _decode_sets(mesh: Mesh) -> Mesh:
    node_sets = dict(mesh.node_sets)
    element_sets = dict(mesh.element_sets)
    pdata, cdata = {}, {}
    for k, v in mesh.point_data.items():
        if k.startswith(NODESET_PREFIX):
            node_sets[k[len(NODESET_PREFIX):]] = np.flatnonzero(v)
        else:
            pdata[k] = v
    for k, v in mesh.cell_data.items():
        if k.startswith(ELSET_PREFIX):
            element_sets[k[len(ELSET_PREFIX):]] = np.flatnonzero(v)
        else:
            cdata[k] = v
    return Mesh(mesh.points, mesh.cells, node_sets, element_sets, pdata, cdata)


def write(path: str | os.PathLike, mesh: Mesh) -> Path:
    """Write ``mesh`` to VTU, XDMF or Abaqus ``.inp`` (by suffix), atomically.

    Abaqus files keep the sets but no fields (the format has none). Meshes may mix
    volume blocks (``hex8``, ``wedge6``, ``tet4``, ``tet10``) in every format; element
    sets may span blocks.
    """
    import meshio

    path = Path(path)
    fmt = _format(path)
    if fmt == "abaqus":  # our writer: each set once, spanning blocks (see toolkit.common.meshes.abaqus)
        with atomic_path(path) as tmp, open(tmp, "w") as f:
            write_abaqus(f, mesh)
        return path
    m = _encode_sets(mesh)
    if fmt == "xdmf":
        # XDMF is two files (.xdmf + .h5); write both in a scratch folder, then move
        with tempfile.TemporaryDirectory(dir=path.parent if path.parent.exists() else None) as scratch_dir:
            scratch = Path(scratch_dir) / path.name
            meshio.write(scratch, m, file_format="xdmf")
            _move_xdmf(scratch, path)
        return path
    with atomic_path(path) as tmp:
        meshio.write(tmp, m, file_format=fmt)
    return path


def _move_xdmf(scratch: Path, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    h5 = scratch.with_suffix(".h5")
    if h5.exists():
        os.replace(h5, path.with_suffix(".h5"))
    os.replace(scratch, path)


def read(
    path: str | os.PathLike,
    units: str = "mm",
    require_node_sets: Iterable[str] = (),
    require_element_sets: Iterable[str] = (),
    check: bool = True,
    require_volume: bool = True,
) -> Mesh:
    """Read a VTU, XDMF or Abaqus ``.inp`` mesh with its sets.

    Parameters
    ----------
    path : file name; the suffix picks the format
    units : length unit of the file (``mm``, ``m``, ``cm``, ``um``); points are
        converted to mm
    require_node_sets, require_element_sets : names that must be present
    check : refuse meshes whose size does not look like mm (see :func:`check_units`)
    require_volume : refuse a mesh without volume cells (a surface mesh)

    Returns
    -------
    Mesh, points ``(n, 3)`` mm
    """
    path = Path(path)
    fmt = _format(path)
    if not path.exists():
        raise FileNotFoundError(f"mesh file {str(path)!r} does not exist")
    if units not in UNIT_SCALES:
        raise ValueError(f"unknown units {units!r}; expected one of {sorted(UNIT_SCALES)}")
    mesh = _decode_sets(_read_meshio(path, fmt))
    if require_volume and mesh.n_volume_cells == 0:
        raise MeshError(
            f"{path.name} holds no volume cells (cell blocks: {_describe_blocks(mesh)}); expected a volume mesh"
            f" of {', '.join(VOLUME_TYPES)}"
        )
    if UNIT_SCALES[units] != 1.0:
        mesh = mesh.with_points(mesh.points * UNIT_SCALES[units])
    if check:
        check_units(mesh, source=f"{path.name}")
    missing = [n for n in require_node_sets if n not in mesh.node_sets]
    missing += [n for n in require_element_sets if n not in mesh.element_sets]
    if missing:
        raise MissingSetError(
            f"{path.name} lacks the sets {missing}; it has node sets {sorted(mesh.node_sets)} and element sets"
            f" {sorted(mesh.element_sets)}"
        )
    return mesh


_FORMAT_NAMES = {"vtu": "a VTU (VTK XML) file", "xdmf": "an XDMF file with its .h5",
                 "abaqus": "an Abaqus .inp text file"}
#: messages of Python's number parsing: the offending text is quoted at the end
_NUMBER_ERROR = re.compile(r"(?:could not convert string to float|invalid literal for int\(\) with base \d+): '(.*)'$")


def _describe_blocks(mesh: Mesh) -> str:
    return ", ".join(f"{t}: {c.shape[0]}" for t, c in mesh.cells.items()) or "none"


def read_text(path: Path, error: type[Exception], expected: str, name: str | None = None) -> str:
    """The UTF-8 text of ``path``; a byte that is not text raises ``error`` naming the file (as
    ``name``, default the path), the line and ``expected`` (e.g. ``"a TOML scene"``)."""
    raw = path.read_bytes()
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        line = raw.count(b"\n", 0, exc.start) + 1
        raise error(f"{name or path}, line {line}: byte 0x{raw[exc.start]:02x} is not text (UTF-8); "
                    f"expected {expected}") from None


def _read_meshio(path: Path, fmt: str) -> Mesh:
    """``meshio`` reading with every failure turned into a :class:`MeshError` that names the file
    (and the line of an Abaqus file where it can be found)."""
    expected = _FORMAT_NAMES[fmt]
    if path.is_dir():
        raise MeshError(f"{path} is a folder; expected {expected}")
    if path.stat().st_size == 0:
        raise MeshError(f"{path.name} is empty (0 bytes); expected {expected}")
    lines = None
    if fmt == "abaqus":
        text = read_text(path, MeshError, expected, name=path.name)
        lines = text.splitlines()
        _check_abaqus_node_ids(path, lines)
    # meshio's own ``read`` prints and calls sys.exit on a file it cannot parse; its per-format
    # readers raise instead
    from meshio._helpers import reader_map

    try:
        if lines is None:
            m = reader_map[fmt](str(path))
        else:
            # meshio ends a *NODE/*ELEMENT/*NSET block at a ``**`` comment line and skips blank ones:
            # blank the comments (line numbers stay)
            from meshio.abaqus._abaqus import read_buffer

            if text.startswith("**") or "\n**" in text:
                text = "\n".join("" if ln.startswith("**") else ln for ln in lines) + "\n"
            m = read_buffer(StringIO(text))
    except (MemoryError, KeyboardInterrupt):
        raise
    except Exception as exc:  # noqa: BLE001 - any parse failure of a third-party reader
        raise MeshError(_parse_failure(path, fmt, exc, lines)) from exc
    try:
        return from_meshio(m)
    except MeshError as exc:
        if np.asarray(m.points).size == 0:
            raise MeshError(f"{path.name} holds no points; expected {expected} with nodes and cells") from exc
        raise MeshError(f"{path.name}: {exc}") from exc


def _parse_failure(path: Path, fmt: str, exc: Exception, lines: list[str] | None) -> str:
    expected = _FORMAT_NAMES[fmt]
    cause: BaseException = exc
    while str(cause) in ("", type(cause).__name__) and (inner := cause.__cause__ or cause.__context__) is not None:
        cause = inner  # meshio's ReadError() wraps the parser's message
    reason = f"{type(cause).__name__}: {cause}" if str(cause) else type(cause).__name__
    if fmt == "xdmf" and isinstance(cause, FileNotFoundError):
        return (f"{path.name} keeps its data in {path.with_suffix('.h5').name}, which cannot be opened"
                f" ({reason}); expected the .h5 file beside the .xdmf")
    if lines is None:
        return f"{path.name} cannot be read as {expected} ({reason}); is it truncated or of another format?"
    token = None
    if isinstance(exc, KeyError):
        token = str(int(exc.args[0])) if exc.args and np.issubdtype(type(exc.args[0]), np.integer) else None
        if token is not None:
            line = _abaqus_line(lines, token, data_only=("*ELEMENT", "*NSET", "*ELSET"))
            where = f", line {line}" if line else ""
            return (f"{path.name}{where}: refers to node or element {token}, which no *NODE or *ELEMENT line"
                    f" defines; expected ids defined in the file")
    match = _NUMBER_ERROR.search(reason)
    if match:
        token = match.group(1)
        line = _abaqus_line(lines, token.strip())
        where = f", line {line}" if line else ""
        return f"{path.name}{where}: {token.strip()!r} is not a number; expected comma-separated numbers"
    named = str(cause).rpartition(": ")[2].strip()
    line = next((k for k, text in enumerate(lines, 1) if named and named.upper() in text.upper()), None)
    where = f", line {line}" if line and named != str(cause) else ""
    return f"{path.name}{where} cannot be read as {expected}: {cause}"


def _abaqus_line(lines: list[str], token: str, data_only: tuple[str, ...] | None = None) -> int | None:
    """1-based number of the first data line holding the field ``token`` (in the given keyword blocks)."""
    keyword = ""
    for k, line in enumerate(lines, 1):
        if line.startswith("**"):  # a comment
            continue
        if line.startswith("*"):
            keyword = line.split(",")[0].strip().upper()
            continue
        if data_only is not None and keyword not in data_only:
            continue
        fields = [f.strip() for f in line.split(",")]
        if data_only is not None and keyword == "*ELEMENT":
            fields = fields[1:]  # the element's own id
        if token in fields:
            return k
    return None


def _check_abaqus_node_ids(path: Path, lines: list[str]) -> None:
    """Refuse a node line with another number of values than the first one, and a node id defined
    twice (meshio would keep the last and renumber the rest)."""
    ids, where, keyword, width = [], [], "", None
    for k, line in enumerate(lines, 1):
        if line.startswith("**"):  # a comment
            continue
        if line.startswith("*"):
            keyword = line.split(",")[0].strip().upper()
        elif keyword == "*NODE" and line.strip():
            values = line.rstrip().rstrip(",").split(",")
            width = width or (len(values), k)
            if len(values) != width[0]:
                raise MeshError(f"{path.name}, line {k}: node line holds {len(values) - 1} coordinates where line"
                                f" {width[1]} holds {width[0] - 1}; expected an id and x, y, z on every *NODE line")
            ids.append(values[0].strip())
            where.append(k)
    if len(set(ids)) == len(ids):
        return
    seen: dict[str, int] = {}
    for node, k in zip(ids, where):
        if node in seen:
            raise MeshError(f"{path.name}, line {k}: node id {node} is defined twice (first on line {seen[node]});"
                            f" expected each *NODE id once")
        seen[node] = k


# ------------------------------------------------------------------ time series
#: XDMF topology names (wedges in meshio's XDMF node order, which is ours)
_XDMF_TOPOLOGY = {"hex8": "Hexahedron", "wedge6": "Wedge", "tet4": "Tetrahedron", "tet10": "Tetrahedron_10",
                  "tri3": "Triangle", "quad4": "Quadrilateral"}
#: XDMF cell type numbers in a ``Mixed`` topology (XdmfTopologyType.hpp)
_XDMF_MIXED_ID = {"tri3": 4, "quad4": 5, "tet4": 6, "wedge6": 8, "hex8": 9, "tet10": 38}


def _mixed_connectivity(cells: Mapping[str, np.ndarray]) -> np.ndarray:
    """The flat XDMF ``Mixed`` array of cell blocks: each cell as its type number then its nodes."""
    return np.concatenate([np.hstack([np.full((conn.shape[0], 1), _XDMF_MIXED_ID[ctype], dtype=np.int64),
                                      np.asarray(conn, dtype=np.int64)]).ravel()
                           for ctype, conn in cells.items()])


@dataclass(frozen=True, eq=False)
class TimeSeries:
    """Fields over time on a fixed mesh.

    Attributes
    ----------
    mesh : Mesh (with its node/element sets)
    times : (n_frames,) float, s
    point_data : mapping name -> (n_frames, n_points, ...) arrays
    """

    mesh: Mesh
    times: np.ndarray
    point_data: Mapping[str, np.ndarray]


class TimeSeriesWriter:
    """Append frames to an XDMF time series (``NAME.xdmf`` + ``NAME.h5``).

    Each :meth:`append` writes the frame's arrays to the HDF5 file, flushes it,
    and atomically rewrites the small XDMF index to list every finished frame, so
    an interrupted run leaves a readable series of the frames it completed. The
    HDF5 file also keeps the mesh's node and element sets (``/mesh/node_sets``,
    ``/mesh/element_sets``), which :func:`read_time_series` restores. ParaView and
    meshio read the XDMF as a standard temporal collection. A mesh of several cell blocks
    (hexahedra and wedges, say) is written as one XDMF ``Mixed`` topology, in block order
    (meshio reads it for linear cells; ParaView for every type).

    Parameters
    ----------
    path : ``*.xdmf``
    mesh : Mesh (one or several cell blocks of ``hex8``, ``wedge6``, ``tet4``, ``tet10``,
        ``tri3``, ``quad4``)
    resume : keep the frames already in an existing series and append after them
    """

    def __init__(self, path: str | os.PathLike, mesh: Mesh, resume: bool = False):
        import h5py

        self.path = Path(path)
        if self.path.suffix.lower() != ".xdmf":
            raise ValueError(f"time series are written as XDMF; got {str(self.path)!r}, expected a '.xdmf' name")
        self.mesh = mesh
        self.h5_path = self.path.with_suffix(".h5")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.times: list[float] = []
        self.fields: dict[str, tuple[int, ...]] = {}
        if resume and self.h5_path.exists():
            self.h5 = h5py.File(self.h5_path, "a")
            self.times = [float(t) for t in self.h5["times"][()]] if "times" in self.h5 else []
            for name, group in self.h5.get("data", {}).items():
                self.fields[name] = group[f"{0:06d}"].shape[1:] if len(group) else ()
            n_done = len(self.times)
            for group in self.h5.get("data", {}).values():  # drop frames written after the last index
                for key in list(group):
                    if int(key) >= n_done:
                        del group[key]
        else:
            ensure_room(self.h5_path, mesh.points.nbytes + sum(c.nbytes for c in mesh.cells.values()))
            self.h5 = h5py.File(self.h5_path, "w")
            self.h5["mesh/points"] = mesh.points
            if len(mesh.cells) == 1:
                (ctype, conn), = mesh.cells.items()
                self.h5["mesh/cells"] = conn
                self.h5["mesh"].attrs["cell_type"] = ctype
            else:  # the XDMF Mixed array, and each block for read_time_series
                self.h5["mesh/cells"] = _mixed_connectivity(mesh.cells)
                self.h5["mesh"].attrs["cell_type"] = "mixed"
                self.h5["mesh"].attrs["cell_types"] = list(mesh.cells)
                for ctype, conn in mesh.cells.items():
                    self.h5[f"mesh/blocks/{ctype}"] = conn
            for name, ids in mesh.node_sets.items():
                self.h5[f"mesh/node_sets/{name}"] = ids
            for name, ids in mesh.element_sets.items():
                self.h5[f"mesh/element_sets/{name}"] = ids
            for name, arr in mesh.cell_data.items():
                self.h5[f"mesh/cell_data/{name}"] = arr
            self.h5.flush()
            self._write_index()

    def __len__(self) -> int:
        return len(self.times)

    def append(self, time: float, **point_data: np.ndarray) -> None:
        """Add one frame: ``time`` in s, fields ``(n_points, ...)`` (e.g. mm, MPa)."""
        k = len(self.times)
        if self.times and not time > self.times[-1]:
            raise ValueError(f"frame times must increase; got {time} after {self.times[-1]}")
        arrays = {name: np.asarray(arr) for name, arr in point_data.items()}
        for name, arr in arrays.items():
            if arr.shape[:1] != (self.mesh.n_points,):
                raise ValueError(f"{name} has shape {arr.shape}, expected ({self.mesh.n_points}, ...)")
            if not np.isfinite(arr).all():
                raise ValueError(f"{name} at t = {time} s holds NaN/inf; refusing to write it to {self.path.name}")
            if self.fields.setdefault(name, arr.shape[1:]) != arr.shape[1:]:
                raise ValueError(f"{name} changed shape from {self.fields[name]} to {arr.shape[1:]}")
        ensure_room(self.h5_path, sum(arr.nbytes for arr in arrays.values()) + 8 * (k + 1))
        for name, arr in arrays.items():
            key = f"data/{name}/{k:06d}"
            if key in self.h5:
                del self.h5[key]
            self.h5[key] = arr
        self.times.append(float(time))
        if "times" in self.h5:
            del self.h5["times"]
        self.h5["times"] = np.asarray(self.times)
        self.h5.flush()
        self._write_index()

    def _write_index(self) -> None:
        from xml.sax.saxutils import quoteattr

        h5 = self.h5_path.name
        n = self.mesh.n_points
        if len(self.mesh.cells) == 1:
            (ctype, conn), = self.mesh.cells.items()
            ne = conn.shape[0]
            topology = (f'<Topology TopologyType="{_XDMF_TOPOLOGY[ctype]}" NumberOfElements="{ne}">'
                        f'<DataItem DataType="Int" Precision="8" Dimensions="{ne} {conn.shape[1]}" Format="HDF">'
                        f'{h5}:/mesh/cells</DataItem></Topology>')
        else:
            ne = sum(conn.shape[0] for conn in self.mesh.cells.values())
            size = self.h5["mesh/cells"].shape[0]
            topology = (f'<Topology TopologyType="Mixed" NumberOfElements="{ne}">'
                        f'<DataItem DataType="Int" Precision="8" Dimensions="{size}" Format="HDF">'
                        f'{h5}:/mesh/cells</DataItem></Topology>')
        geometry = (f'<Geometry GeometryType="XYZ"><DataItem DataType="Float" Precision="8" Dimensions="{n} 3"'
                    f' Format="HDF">{h5}:/mesh/points</DataItem></Geometry>')
        parts = ['<?xml version="1.0"?>', '<Xdmf Version="3.0"><Domain>']
        if not self.times:  # the mesh alone, so that a series stopped before its first frame still opens
            parts.append(f'<Grid Name="mesh" GridType="Uniform">{topology}{geometry}</Grid>')
        parts.append('<Grid Name="TimeSeries" GridType="Collection" CollectionType="Temporal">')
        for k, t in enumerate(self.times):
            parts.append(f'<Grid Name="frame_{k}" GridType="Uniform"><Time Value="{t!r}"/>')
            parts.append(topology)
            parts.append(geometry)
            for name, shape in self.fields.items():
                kind = {(): "Scalar", (3,): "Vector"}.get(shape, "Tensor" if shape == (3, 3) else "Matrix")
                dims = " ".join(str(d) for d in (n,) + shape)
                dtype = self.h5[f"data/{name}/{k:06d}"].dtype
                num = "Float" if dtype.kind == "f" else "Int"
                parts.append(f'<Attribute Name={quoteattr(name)} AttributeType="{kind}" Center="Node">'
                             f'<DataItem DataType="{num}" Precision="{dtype.itemsize}" Dimensions="{dims}"'
                             f' Format="HDF">{h5}:/data/{name}/{k:06d}</DataItem></Attribute>')
            parts.append("</Grid>")
        parts.append("</Grid></Domain></Xdmf>")
        with atomic_path(self.path) as tmp:
            tmp.write_text("\n".join(parts))

    def close(self) -> None:
        if self.h5.id:
            self.h5.close()

    def __enter__(self) -> TimeSeriesWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


#: bytes an HDF5 write needs beyond its data (object headers, the metadata cache's flush), and the
#: share of the data added for chunk and heap overhead
_HDF5_OVERHEAD = (256 * 1024, 0.05)


def ensure_room(path: str | os.PathLike, nbytes: int, *, anew: bool = False) -> None:
    """Raise ``OSError`` (``ENOSPC``: the disk; ``EFBIG``: the process's file-size limit) when
    ``path`` cannot grow by ``nbytes`` plus HDF5's overhead (``anew``: when a file of that size,
    a copy written beside ``path``, cannot be written), before anything is written.

    HDF5 buffers its writes: one that fails on a full disk is reported late or not at all, and
    the next call into the library can crash the process. Checking the room first turns a full
    disk into an error the caller handles (the command line's one ``error:`` line, its partial
    files removed)."""
    fixed, share = _HDF5_OVERHEAD
    need = int(nbytes * (1 + share)) + fixed
    path = Path(path)
    free = shutil.disk_usage(path.parent if path.parent.exists() else Path.cwd()).free
    if free < need:
        raise OSError(errno.ENOSPC, f"No space left on device: {need / 2**20:.1f} MiB needed, "
                                    f"{free / 2**20:.1f} MiB free", str(path))
    try:
        import resource
    except ImportError:  # Windows: no file-size limit to read
        return
    limit = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    size = path.stat().st_size if path.exists() and not anew else 0
    if limit != resource.RLIM_INFINITY and size + need > limit:
        raise OSError(errno.EFBIG, f"File too large: {size + need} bytes needed, the process may write files of "
                                   f"{limit} bytes (ulimit -f)", str(path))


def write_time_series(
    path: str | os.PathLike,
    mesh: Mesh,
    times: np.ndarray,
    point_data: Mapping[str, np.ndarray],
) -> Path:
    """Write a whole XDMF time series at once (see :class:`TimeSeriesWriter`).

    Parameters
    ----------
    path : ``*.xdmf``
    mesh : Mesh (one or several cell blocks)
    times : (n_frames,) s
    point_data : name -> (n_frames, n_points, ...) e.g. ``displacement`` in mm
    """
    times = np.asarray(times, dtype=float)
    for name, arr in point_data.items():
        if np.shape(arr)[:2] != (times.size, mesh.n_points):
            raise ValueError(
                f"point_data[{name!r}] has shape {np.shape(arr)}, expected ({times.size}, {mesh.n_points}, ...)"
            )
    with TimeSeriesWriter(path, mesh) as writer:
        for k, t in enumerate(times):
            writer.append(t, **{name: arr[k] for name, arr in point_data.items()})
    return Path(path)


def read_time_series(path: str | os.PathLike) -> TimeSeries:
    """Read a series written by :class:`TimeSeriesWriter` (frames listed in the XDMF)."""
    import h5py

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"time series {str(path)!r} does not exist")
    h5_path = path.with_suffix(".h5")
    with h5py.File(h5_path, "r") as h5:
        if "mesh" not in h5 or "cell_type" not in h5["mesh"].attrs:
            raise ValueError(f"{h5_path.name} was not written by toolkit's TimeSeriesWriter (no /mesh group)")
        g = h5["mesh"]
        if g.attrs["cell_type"] == "mixed":
            cells = {str(ctype): g[f"blocks/{ctype}"][()] for ctype in g.attrs["cell_types"]}
        else:
            cells = {g.attrs["cell_type"]: g["cells"][()]}
        mesh = Mesh(
            g["points"][()],
            cells,
            node_sets={k: v[()] for k, v in g.get("node_sets", {}).items()},
            element_sets={k: v[()] for k, v in g.get("element_sets", {}).items()},
            cell_data={k: v[()] for k, v in g.get("cell_data", {}).items()},
        )
        times = h5["times"][()] if "times" in h5 else np.zeros(0)
        n = times.size
        data = {name: np.stack([grp[f"{k:06d}"][()] for k in range(n)]) if n else np.zeros((0, mesh.n_points))
                for name, grp in h5.get("data", {}).items()}
    return TimeSeries(mesh, np.asarray(times, dtype=float), data)
