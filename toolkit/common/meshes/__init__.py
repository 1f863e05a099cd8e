"""Meshes and surfaces: the :class:`~toolkit.common.meshes.mesh.Mesh` container (``mesh``), element
quality (``quality``), topology (``topology``), conversions to meshio, pyvista and scikit-fem
(``convert``), mesh files (``io``, ``abaqus``), anatomical axes (``axes``) and the triangle
surfaces segmentation and planning systems export (``surfaces``)."""
