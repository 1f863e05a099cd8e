"""A patient's face from segmented surfaces: repair, tetrahedral meshing, labelling.

:func:`mesh_face` is the whole pipeline (``toolkit mesh`` on the command line); the stages are
:mod:`~toolkit.mesh.surface` (repair), :mod:`~toolkit.mesh.backends` (meshers),
:mod:`~toolkit.mesh.mouth` (the lip slit), :mod:`~toolkit.mesh.labels` and
:mod:`~toolkit.mesh.rules` (node sets).
"""

from toolkit.mesh.backends import BACKENDS, DEFAULT, MeshingError, available, tetrahedralize
from toolkit.mesh.face import FaceInputError, MeshedFace, mesh_face
from toolkit.mesh.rules import LabelRules, RulesError, read_rules
from toolkit.mesh.surface import SurfaceError, closed_surface, read_tissue_surface

__all__ = ["BACKENDS", "DEFAULT", "MeshingError", "available", "tetrahedralize", "FaceInputError", "MeshedFace",
           "mesh_face", "LabelRules", "RulesError", "read_rules", "SurfaceError", "closed_surface",
           "read_tissue_surface"]
