"""Facial soft-tissue biomechanics toolkit.

Two workflows on one core of meshes, materials and metrics:

- :mod:`toolkit.static`: incremental FEM of the face after orthognathic surgery
  (and its PointNet++ surrogate);
- :mod:`toolkit.impact`: elastoplastic ball-impact simulation, quasi-static or explicit (and its
  LSTM surrogate);
- :mod:`toolkit.common`: meshes, phantoms, I/O, metrics and plotting.

Units everywhere: mm, s, tonne, N, MPa.

Every error the toolkit raises on purpose derives from :class:`ToolkitError`
(:mod:`toolkit.common.errors`).

Importing the package changes nothing in the process (no environment variable, no thread
limit). On 2 cores, two BLAS and torch threads are no faster than one for the toolkit's kernels,
or slower (``benchmarks/threads.py``), so the command line runs on one thread (``--threads``);
in Python call :func:`toolkit.set_threads` (``set_threads(1)``, or ``set_threads()`` for
``TOOLKIT_NUM_THREADS``, default 1) before heavy work.
"""

from toolkit.common.errors import AnswerError, ConvergenceError, ToolkitError
from toolkit.common.runtime import set_threads

__version__ = "0.1.0"
__all__ = ["set_threads", "ToolkitError", "ConvergenceError", "AnswerError", "__version__"]
