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

__all__ = ["STATIC_SIMULATION", "MESH", "MIN_CARRIED_MM2", "MIN_CARRIED_SHARE"]

#: phantom resolution, load increments, tissue material and sliding of a static simulation
STATIC_SIMULATION: MappingProxyType[str, Any] = MappingProxyType(
    {"resolution": "coarse", "increments": 3, "material": "linear", "sliding": "mucosa+lip"})

#: a meshed face's tetrahedron edge length (mm; a paper-size face: a few thousand nodes) and element
#: order (quadratic: linear tetrahedra lock at nu = 0.47)
MESH: MappingProxyType[str, Any] = MappingProxyType({"size_mm": 3.0, "order": 2})

#: mm^2, the least tissue boundary area a moving segment (Le Fort I, distal mandible) must carry
#: (lumped nodal area of its attached set), in the labelling and before a plan moves it. The
#: phantoms' Le Fort I segments carry 640 (coarse) and 940 mm^2 (paper), their distal mandibles
#: 1,870 and 1,450 mm^2; a real jaw carries the attached gingiva and periosteum of its front,
#: several cm^2. A segment below 40 mm^2 holds a few nodes at most: a labelling that failed, not an
#: anatomy.
MIN_CARRIED_MM2 = 40.0
#: the least share of the tissue lying on a moving segment's bone (carried or sliding) that the
#: segment must carry. The front of a jaw, where the attached gingiva and the periosteum hold the
#: tissue, is about a third of the bone the tissue lies on: the phantoms' segments carry 0.29-0.38 of
#: it (hexahedral, coarse to fine) and 0.32-0.40 meshed, the head CT's 0.29 (Le Fort I and distal
#: mandible alike). A segment carrying less than 0.05,
#: a sixth of the least of these, holds a strip of its front edge: the rule that chose what it
#: carries (``segments.<name>.attach``) or the bone's placement went wrong, whatever the mesh size.
MIN_CARRIED_SHARE = 0.05
