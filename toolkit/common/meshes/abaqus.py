"""Abaqus ``.inp`` mesh decks: the writer (meshio reads them).

meshio's own writer repeats an ``*ELSET`` once per cell block, and its reader keeps only
the last definition of a name, so an element set spanning several blocks (a region of
a mixed hex/wedge/tet mesh) would lose members on a round trip; it also names
hexahedra ``C3D8RH``. This writer gives every set once, with global 1-based ids, and
names each block by its reference element's first Abaqus name (``C3D8``, ``C3D6``,
``C3D4``, ``C3D10``, ``S3``, ``S4``). Node order is the reference elements', which is
Abaqus's for every type here. Units are those of the mesh (mm); fields are not
written (the format has none).
"""

from __future__ import annotations

from typing import TextIO

import numpy as np

from toolkit.common.fem.reference import REFERENCE_ELEMENTS
from toolkit.common.meshes.mesh import Mesh

__all__ = ["write_abaqus"]

#: entries per data line of a set (Abaqus allows at most 16)
_PER_LINE = 16


def _id_lines(ids: np.ndarray) -> str:
    """1-based ids, ``_PER_LINE`` to a line."""
    ids = np.asarray(ids, dtype=np.int64) + 1
    rows = [", ".join(map(str, ids[i:i + _PER_LINE].tolist())) for i in range(0, ids.size, _PER_LINE)]
    return "\n".join(rows) + "\n"


def write_abaqus(f: TextIO, mesh: Mesh, heading: str = "written by toolkit") -> None:
    """Write ``mesh`` (nodes, element blocks, node and element sets) to the text stream ``f``.

    Element ids are the global element indices + 1 (block order), node ids the point
    indices + 1, so a deck read back with :func:`toolkit.common.meshes.io.read` gives the same
    numbering.
    """
    f.write(f"*HEADING\n{heading}\n*NODE\n")
    ids = np.arange(1, mesh.n_points + 1)[:, None]
    np.savetxt(f, np.hstack([ids, mesh.points]), fmt=["%d"] + ["%.16e"] * 3, delimiter=", ")
    for block in mesh.blocks:
        f.write(f"*ELEMENT, TYPE={REFERENCE_ELEMENTS[block.ctype].abaqus[0]}\n")
        rows = np.hstack([block.elements[:, None] + 1, block.cells + 1])
        np.savetxt(f, rows, fmt="%d", delimiter=", ")
    for name, members in mesh.node_sets.items():
        f.write(f"*NSET, NSET={name}\n")
        if members.size:
            f.write(_id_lines(members))
    for name, members in mesh.element_sets.items():
        f.write(f"*ELSET, ELSET={name}\n")
        if members.size:
            f.write(_id_lines(members))
