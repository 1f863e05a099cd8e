"""A patient's face from segmented surfaces: repair, tetrahedral meshing, labelling.

:func:`mesh_face` is the whole pipeline (``toolkit mesh`` on the command line); the stages are
:mod:`~toolkit.mesh.surface` (repair), :mod:`~toolkit.mesh.backends` (meshers),
:mod:`~toolkit.mesh.mouth` (the lip slit), :mod:`~toolkit.mesh.labels` and
:mod:`~toolkit.mesh.rules` (node sets). From a head CT, :func:`ct_surfaces` (``toolkit ct``;
:mod:`~toolkit.mesh.ct`, :mod:`~toolkit.mesh.ct_anatomy`, :mod:`~toolkit.mesh.volume`) makes
the surfaces it takes.
"""

import importlib

#: public name -> the module that holds it (imported when first used: the command line builds its
#: parser from this package without loading the meshing code)
_EXPORTS = {
    **dict.fromkeys(["BACKENDS", "DEFAULT", "MeshingError", "available", "tetrahedralize"], "backends"),
    **dict.fromkeys(["CTError", "CTRules", "CTSurfaces", "ct_surfaces"], "ct"),
    **dict.fromkeys(["FaceInputError", "MeshedFace", "mesh_face"], "face"),
    **dict.fromkeys(["LabelRules", "RulesError", "read_rules"], "rules"),
    **dict.fromkeys(["SurfaceError", "closed_surface", "read_tissue_surface"], "surface"),
    **dict.fromkeys(["Volume", "VolumeError", "read_volume"], "volume"),
}
__all__ = list(_EXPORTS)


def __getattr__(name: str):
    if name not in _EXPORTS:
        raise AttributeError(f"module 'toolkit.mesh' has no attribute {name!r}")
    return getattr(importlib.import_module(f"toolkit.mesh.{_EXPORTS[name]}"), name)


def __dir__():
    return sorted(__all__)
