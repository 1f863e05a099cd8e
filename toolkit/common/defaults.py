"""The defaults of a static simulation and of meshing a face, read by the command line and the
Python API alike.

:func:`toolkit.static.load_case`, :func:`toolkit.static.simulate`,
:class:`toolkit.static.database.DatabaseConfig` and ``toolkit static simulate|database`` take
:data:`STATIC_SIMULATION` when an option is neither given nor chosen by a tolerance;
:func:`toolkit.mesh.mesh_face` and ``toolkit mesh`` take :data:`MESH`. The impact workflow's defaults are
its dataclasses' (:class:`toolkit.impact.scene.Fidelity`, :func:`toolkit.impact.default_scene`),
which its command line reads from the scene.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

__all__ = ["STATIC_SIMULATION", "MESH"]

#: phantom resolution, load increments, tissue material and sliding of a static simulation
STATIC_SIMULATION: MappingProxyType[str, Any] = MappingProxyType(
    {"resolution": "coarse", "increments": 3, "material": "linear", "sliding": "mucosa+lip"})

#: a meshed face's tetrahedron edge length (mm; a paper-size face: a few thousand nodes) and element
#: order (quadratic: linear tetrahedra lock at nu = 0.47)
MESH: MappingProxyType[str, Any] = MappingProxyType({"size_mm": 3.0, "order": 2})
