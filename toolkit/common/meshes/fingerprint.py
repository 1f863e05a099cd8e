"""Fingerprints that tell whether a mesh is the one a database or a model was made on.

Two identities are checked, for two questions:

- :func:`points_fingerprint`: the same face (the reference coordinates, rounded to 1e-6 mm so
  that a round trip through a file does not change it). A model trained on one face answers
  only for it (the impact surrogate; a static model's training subjects).
- :func:`mesh_fingerprint`: the same node count and element connectivity, whatever the
  coordinates (a new subject of the phantom's topology is a valid input to a static model).

:func:`file_fingerprint` identifies the file a database was built from (a resumed database
refuses a mesh or bone file that changed) and the weights a calibration was made for.
"""

from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping
from pathlib import Path

import numpy as np

__all__ = ["points_fingerprint", "topology_fingerprint", "mesh_fingerprint", "array_fingerprint", "file_fingerprint"]


def array_fingerprint(values: np.ndarray) -> str:
    """16 hex digits of the SHA-256 of ``values`` as contiguous int64 (integer arrays: node
    types, connectivity) or float64 (anything else)."""
    values = np.asarray(values)
    dtype = np.int64 if np.issubdtype(values.dtype, np.integer) or values.dtype == bool else np.float64
    return hashlib.sha256(np.ascontiguousarray(values, dtype=dtype).tobytes()).hexdigest()[:16]


def points_fingerprint(points: np.ndarray) -> str:
    """Fingerprint of the coordinates ``(n, 3)`` mm, rounded to 1e-6 mm (``-0.0`` counts as ``0.0``)."""
    return array_fingerprint(np.round(np.asarray(points, dtype=np.float64), 6) + 0.0)


def topology_fingerprint(cells: Mapping[str, np.ndarray]) -> str:
    """Fingerprint of the connectivity: every block's cell type and node indices, in the order of
    the cell type names."""
    h = hashlib.sha256()
    for ctype in sorted(cells):
        h.update(ctype.encode())
        h.update(np.ascontiguousarray(cells[ctype], dtype=np.int64).tobytes())
    return h.hexdigest()[:16]


def mesh_fingerprint(points: np.ndarray, cells: Mapping[str, np.ndarray]) -> dict:
    """What a model checks about a mesh of a new subject: ``{"nodes": n, "topology": str}`` (not
    the coordinates)."""
    return {"nodes": int(np.shape(points)[0]), "topology": topology_fingerprint(cells)}


def file_fingerprint(path: str | os.PathLike) -> str:
    """SHA-1 (40 hex digits) of a file's bytes."""
    return hashlib.sha1(Path(path).read_bytes()).hexdigest()
