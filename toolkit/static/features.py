"""Per-node input channels of the static surrogate (the PointNet++ paper and the switches beyond it).

The PointNet++ paper feeds PointNet++, per node: the coordinates of the starting mesh (mm), the
boundary type as a one-hot ``free = [1, 0, 0]``, ``moving = [0, 1, 0]``, ``fixed = [0, 0, 1]``
(*explicit*; sliding nodes count as free) or nothing (*implicit*), and the prescribed
displacement ``s`` (mm; zero at nodes that are not moving). Two switches add channels:

- ``extra_channels``: the sliding nodes get their own one-hot columns (mucosa, lip), a
  side channel tells the upper jaw and lip (+1) from the lower ones (-1), and the mucosa
  nodes carry the displacement their bone would give them (mm). Without them the two
  copies of a point on the closed mouth slit (and the coincident mucosa nodes at its
  inner edge) get identical inputs although they move millimetres apart;
- ``material_channels``: Poisson's ratio per node (for databases whose simulations vary it);
- ``linear_prior``: the linear influence-matrix solution of the increment
  (:class:`~toolkit.static.baselines.InfluenceMatrix`, mm) as three channels; the network then
  learns only what the linear superposition misses (sliding, lip contact, the geometry
  update), and the surrogate adds the prior back (:mod:`toolkit.static.surrogate`).

:func:`encode` builds the ``(n, C)`` array of one sample; :func:`channel_names` names
the columns (units in the names).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FeatureSpec", "encode", "channel_names", "VARIANTS"]

#: explicit boundary types (the PointNet++ paper), implicit (none), hard (explicit + exact boundary values)
VARIANTS = ("explicit", "implicit", "hard")


@dataclass(frozen=True)
class FeatureSpec:
    """Which channels a model reads.

    Attributes
    ----------
    variant : ``explicit``, ``implicit`` or ``hard`` (hard reads what explicit reads)
    extra_channels : mucosa/lip one-hot, jaw side, mucosa bone displacement
    material_channels : Poisson's ratio
    linear_prior : the influence-matrix displacement as input, the residual as output
    """

    variant: str = "explicit"
    extra_channels: bool = False
    material_channels: bool = False
    linear_prior: bool = False

    def __post_init__(self):
        if self.variant not in VARIANTS:
            raise ValueError(f"variant = {self.variant!r}; expected one of {VARIANTS}")

    @property
    def n_channels(self) -> int:
        return len(channel_names(self))


def channel_names(spec: FeatureSpec) -> tuple[str, ...]:
    """Names of the input columns, in order."""
    names = ["x_mm", "y_mm", "z_mm"]
    if spec.variant != "implicit":
        names += ["free", "moving", "fixed"]
        if spec.extra_channels:
            names += ["mucosa", "lip"]
    if spec.extra_channels:
        names += ["jaw_side"]
    names += ["s_x_mm", "s_y_mm", "s_z_mm"]
    if spec.extra_channels:
        names += ["bone_x_mm", "bone_y_mm", "bone_z_mm"]
    if spec.material_channels:
        names += ["poisson_ratio"]
    if spec.linear_prior:
        names += ["prior_x_mm", "prior_y_mm", "prior_z_mm"]
    return tuple(names)


def encode(spec: FeatureSpec, x: np.ndarray, types: np.ndarray, s: np.ndarray, bone: np.ndarray | None = None,
           side: np.ndarray | None = None, poisson: float | None = None, prior: np.ndarray | None = None) -> np.ndarray:
    """Input channels ``(n, C)`` of one sample.

    Parameters
    ----------
    x : (n, 3) mm — starting mesh
    types : (n,) int — boundary types (0 free, 1 moving, 2 fixed, 3 mucosa, 4 lip)
    s : (n, 3) mm — prescribed displacement (zero where not moving)
    bone : (n, 3) mm — the bone's displacement at every bone-driven node (extra channels)
    side : (n,) — +1 upper jaw/lip, -1 lower, 0 elsewhere (extra channels)
    poisson : Poisson's ratio of the simulation (material channels)
    prior : (n, 3) mm — the linear influence-matrix displacement (linear prior)
    """
    x = np.asarray(x, dtype=float)
    n = x.shape[0]
    types = np.asarray(types).reshape(-1)
    if types.shape != (n,) or np.shape(s) != (n, 3):
        raise ValueError(f"types {types.shape} and s {np.shape(s)} must be ({n},) and ({n}, 3) for {n} nodes")
    cols = [x]
    if spec.variant != "implicit":
        kinds = (1, 2, 3, 4) if spec.extra_channels else (1, 2)
        onehot = np.zeros((n, 1 + len(kinds)))
        onehot[:, 0] = 1.0
        for c, t in enumerate(kinds, start=1):
            onehot[types == t, 0] = 0.0
            onehot[types == t, c] = 1.0
        cols.append(onehot)
    if spec.extra_channels:
        if side is None or bone is None:
            raise ValueError("extra_channels needs the jaw side (n,) and the bone displacement (n, 3)")
        cols.append(np.asarray(side, dtype=float).reshape(n, 1))
    cols.append(np.where((types == 1)[:, None], np.asarray(s, dtype=float), 0.0))
    if spec.extra_channels:
        cols.append(np.where((types == 3)[:, None], np.asarray(bone, dtype=float), 0.0))
    if spec.material_channels:
        if poisson is None:
            raise ValueError("material_channels needs the simulation's Poisson's ratio")
        cols.append(np.full((n, 1), float(poisson)))
    if spec.linear_prior:
        if prior is None or np.shape(prior) != (n, 3):
            raise ValueError(f"linear_prior needs the influence-matrix displacement ({n}, 3), got "
                             f"{None if prior is None else np.shape(prior)}")
        cols.append(np.asarray(prior, dtype=float))
    return np.hstack(cols)
