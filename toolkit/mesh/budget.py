"""What a ``toolkit mesh`` size will cost, estimated from the tissue surface before meshing.

Elements: ``a V / s^3 + b A / s^2`` for a closed tissue surface of volume ``V`` mm^3 and area
``A`` mm^2 at edge length ``s`` mm, the bulk and the boundary layer of a face (a shell ~10-20 mm
thick, so the boundary term matters). ``a``, ``b`` are fitted to fTetWild's meshes of the paper
phantom's surfaces at 7, 5, 4 and 3 mm (their element counts, against which the fit is checked:
``benchmarks/mesh_convergence.py``). fTetWild keeps the input surface's triangles, so a surface
finer than ``s`` (a CT's voxel-sized triangles) gives more elements than this.

Memory, the larger of two stages:

- the simulation of a plan on the tet10 face: :data:`SIMULATION_BASE_GIB` plus
  :data:`SIMULATION_GIB_PER_ELEMENT` per element (a line through the peak resident memory of the
  default plan at those four sizes, ``benchmarks/mesh_convergence.py``); a tet4 face needs less,
  and is given the same figure as a bound;
- the mesher: :data:`MESHER_KIB_PER_ELEMENT` per final element (set from fTetWild's memory at
  0.5 mm on the paper phantom's surfaces, a mesh of millions of elements).
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np

__all__ = ["SizeEstimate", "estimate_size", "available_memory_gib", "finest_fitting_size"]

#: elements per ``V / s^3`` and per ``A / s^2`` (fitted, see the module)
BULK, BOUNDARY = 6.69, 4.57
#: nodes per element (tet4, tet10): within the range of the paper phantom's meshes at 3-7 mm and the
#: head CT's (``benchmarks/mesh_convergence.py``, ``benchmarks/real_ct.py``)
NODES_PER_ELEMENT = {1: 0.23, 2: 1.6}
SIMULATION_BASE_GIB = 0.38
SIMULATION_GIB_PER_ELEMENT = 3.8e-5
MESHER_KIB_PER_ELEMENT = 1.8


@dataclass(frozen=True)
class SizeEstimate:
    """The expected mesh of one size: ``elements``, ``nodes``, and the peak memory in GiB of
    meshing (``mesher_gib``) and of simulating a plan on it (``simulation_gib``)."""

    size_mm: float
    elements: int
    nodes: int
    mesher_gib: float
    simulation_gib: float

    @property
    def peak_gib(self) -> float:
        """The larger of the two stages' memory, GiB."""
        return max(self.mesher_gib, self.simulation_gib)


def _volume_area(points: np.ndarray, triangles: np.ndarray) -> tuple[float, float]:
    a, b, c = (points[triangles[:, k]] for k in range(3))
    area = 0.5 * float(np.linalg.norm(np.cross(b - a, c - a), axis=1).sum())
    volume = abs(float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum())) / 6.0
    return volume, area


def estimate_size(points: np.ndarray, triangles: np.ndarray, size_mm: float, order: int = 2) -> SizeEstimate:
    """The :class:`SizeEstimate` of meshing the closed surface ``points (n, 3)`` mm,
    ``triangles (m, 3)`` at ``size_mm`` in elements of ``order`` (1: tet4, 2: tet10)."""
    volume, area = _volume_area(np.asarray(points, float), np.asarray(triangles, np.int64))
    s = float(size_mm)
    elements = BULK * volume / s**3 + BOUNDARY * area / s**2
    return SizeEstimate(s, int(round(elements)), int(round(NODES_PER_ELEMENT[int(order)] * elements)),
                        MESHER_KIB_PER_ELEMENT * elements / 2**20,
                        SIMULATION_BASE_GIB + SIMULATION_GIB_PER_ELEMENT * elements)


def available_memory_gib() -> float | None:
    """Memory the system can give a new process, GiB (``MemAvailable`` of ``/proc/meminfo``, else
    the physical memory), or None where neither can be read."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) / 2**20
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return None


def finest_fitting_size(points: np.ndarray, triangles: np.ndarray, memory_gib: float, order: int = 2) -> float:
    """The smallest edge length, mm (to 0.1 mm, rounded up), whose estimated peak memory fits in
    ``memory_gib``."""
    lo, hi = 0.3, 20.0
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if estimate_size(points, triangles, mid, order).peak_gib <= memory_gib:
            hi = mid
        else:
            lo = mid
    return float(np.ceil(hi * 10.0) / 10.0)
