"""The defaults of a static simulation, read by the command line and the Python API alike.

:func:`toolkit.static.load_case`, :func:`toolkit.static.simulate`,
:class:`toolkit.static.dataset.DatasetConfig` and ``toolkit static simulate|dataset`` take these
when an option is neither given nor chosen by a tolerance. The impact workflow's defaults are
its dataclasses' (:class:`toolkit.impact.scene.Fidelity`, :func:`toolkit.impact.default_scene`),
which its command line reads from the scene.
"""

from __future__ import annotations

from types import MappingProxyType
from typing import Any

__all__ = ["STATIC_SIMULATION"]

#: phantom resolution, load increments, tissue material and sliding of a static simulation
STATIC_SIMULATION: MappingProxyType[str, Any] = MappingProxyType(
    {"resolution": "coarse", "increments": 3, "material": "linear", "sliding": "mucosa+lip"})
