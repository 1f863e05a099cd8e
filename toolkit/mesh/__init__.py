"""Volume meshes of a patient's tissue surface."""

from toolkit.mesh.backends import BACKENDS, DEFAULT, MeshingError, available, tetrahedralize

__all__ = ["BACKENDS", "DEFAULT", "MeshingError", "available", "tetrahedralize"]
