"""Facial soft-tissue biomechanics toolkit.

Two workflows on one core of meshes, materials and metrics:

- :mod:`toolkit.static`: incremental FEM of the face after orthognathic surgery
  (and its PointNet++ surrogate);
- :mod:`toolkit.impact`: explicit elastoplastic ball-impact simulation (and its LSTM
  surrogate);
- :mod:`toolkit.common`: meshes, phantoms, I/O, metrics and plotting.

Units everywhere: mm, s, tonne, N, MPa.

On import the numerical libraries default to **one thread**: on the 2-core machines
this project runs on, multithreaded BLAS and torch were measured several times
slower (see SPEC.md). Raise it with ``TOOLKIT_NUM_THREADS=n`` in the environment or
:func:`toolkit.set_threads`.
"""

import os as _os

# Must happen before numpy/scipy/torch load their thread pools.
_threads = _os.environ.get("TOOLKIT_NUM_THREADS", "1")
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, _threads)

from toolkit.common.runtime import set_threads  # noqa: E402

set_threads(None)

__version__ = "0.1.0"
__all__ = ["set_threads", "__version__"]
