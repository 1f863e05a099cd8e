"""The finite-element core shared by both workflows: one reference-element record per cell type (shape
functions, quadrature, faces, edges, file-format names), the fixed-pattern sparse assembly
(:mod:`~toolkit.common.fem.assembly`), the elastic laws (:mod:`~toolkit.common.fem.materials`) and
the lip's fibre direction (:mod:`~toolkit.common.fem.fibres`), material tangents by differentiating
a material's update (:mod:`~toolkit.common.fem.tangent`), the sparse solvers
(:class:`~toolkit.common.fem.solvers.LinearSolver`, composed of the factor backends in
:mod:`~toolkit.common.fem.factors` with MKL PARDISO in :mod:`~toolkit.common.fem.pardiso`, the
orderings in :mod:`~toolkit.common.fem.ordering`, the factor maker in
:mod:`~toolkit.common.fem.factory`, the reuse policy in :mod:`~toolkit.common.fem.reuse`, the
factorize-ahead worker in :mod:`~toolkit.common.fem.ahead`, the Krylov iterations in
:mod:`~toolkit.common.fem.krylov` and the Woodbury correction of a reused factor in
:mod:`~toolkit.common.fem.woodbury`) and Newton's method with its line searches and load-step
cutting (:mod:`~toolkit.common.fem.newton`). Imports nothing from :mod:`toolkit.static` or
:mod:`toolkit.impact`.
"""

from toolkit.common.fem.quadrature import gauss_hex, gauss_line, gauss_quad, tet_rule, triangle_rule, wedge_rule
from toolkit.common.fem.reference import (
    REFERENCE_ELEMENTS,
    TET_EDGES,
    WEDGE_VTK_ORDER,
    ReferenceElement,
    reference_element,
)

__all__ = [
    "ReferenceElement",
    "REFERENCE_ELEMENTS",
    "reference_element",
    "TET_EDGES",
    "WEDGE_VTK_ORDER",
    "gauss_line",
    "gauss_quad",
    "gauss_hex",
    "triangle_rule",
    "tet_rule",
    "wedge_rule",
]
