"""The shared core, in packages named for what they hold: :mod:`~toolkit.common.meshes` (meshes,
their files, surfaces and axes), :mod:`~toolkit.common.fem` (elements, materials, solvers,
Newton), :mod:`~toolkit.common.phantoms` (synthetic meshes with known answers),
:mod:`~toolkit.common.training` (learning and the job database) and
:mod:`~toolkit.common.analysis` (metrics); errors, runtime settings, plotting and the papers'
numbers at the top.

Imports nothing from :mod:`toolkit.static` or :mod:`toolkit.impact`.
"""

from toolkit.common.errors import ConvergenceError, ToolkitError
from toolkit.common.fidelity import FidelityChoice, FidelityError, choose_fidelity
from toolkit.common.meshes.axes import AXES, AxesError, check_anatomical_axes, mesh_to_toolkit, to_toolkit
from toolkit.common.meshes.fingerprint import mesh_fingerprint, points_fingerprint
from toolkit.common.meshes.io import TimeSeries, TimeSeriesWriter, read, read_time_series, write, write_time_series
from toolkit.common.meshes.mesh import (
    CELL_TYPES,
    CellBlock,
    DegenerateElementError,
    InvertedElementError,
    Mesh,
    MeshError,
)
from toolkit.common.phantoms.mixed_bar import mixed_bar
from toolkit.common.phantoms.phantom import BoneSegment, FacePhantom, FaceShape, ball, ball_density, face_hex, face_tet
from toolkit.common.runtime import set_threads
from toolkit.common.training.evaluation import Evaluation

__all__ = [
    "ToolkitError",
    "ConvergenceError",
    "Mesh",
    "MeshError",
    "InvertedElementError",
    "DegenerateElementError",
    "CELL_TYPES",
    "CellBlock",
    "FaceShape",
    "FacePhantom",
    "BoneSegment",
    "face_hex",
    "face_tet",
    "ball",
    "ball_density",
    "mixed_bar",
    "read",
    "write",
    "read_time_series",
    "write_time_series",
    "TimeSeries",
    "TimeSeriesWriter",
    "set_threads",
    "choose_fidelity",
    "FidelityChoice",
    "FidelityError",
    "AXES",
    "AxesError",
    "to_toolkit",
    "mesh_to_toolkit",
    "check_anatomical_axes",
    "points_fingerprint",
    "mesh_fingerprint",
    "Evaluation",
]
