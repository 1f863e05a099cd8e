"""The architecture and neighbourhoods of the face PointNet++ (:class:`PointNet2Config`), without torch:
the training code (:mod:`toolkit.static.pointnet2`) and the numpy inference
(:mod:`toolkit.static.pointnet2_inference`) read the same configuration."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

__all__ = ["PointNet2Config"]


def _tuple(value, depth: int = 1):
    if depth == 1:
        return tuple(value)
    return tuple(_tuple(v, depth - 1) for v in value)


@dataclass(frozen=True)
class PointNet2Config:
    """Architecture and neighbourhoods of :class:`PointNet2` (one entry per level, finest first).

    Attributes
    ----------
    in_channels : int — features per node: e.g. 6 for coordinates + prescribed displacement
        (the PointNet++ paper's "implicit"), 9 with the free/moving/fixed one-hot ("explicit"), 11 with
        mucosa and lip sliding channels, plus one per material parameter
    out_channels : int — outputs per node (3: displacement)
    centers : per level, the number of sampled centres: an ``int`` is a count, a ``float`` in
        ``(0, 1]`` a fraction of the previous level (rounded up). The default quarters each
        level: 4,100 nodes -> 1,025 / 257 / 65 / 17 centres (the PointNet++ paper's PointNet++ used
        1,024 / 256 / 64 / 16); 771 nodes -> 193 / 49 / 13 / 4.
    radii : per level, ball radius in normalised units (the mesh scaled into ``[-1, 1]^3`` by
        its largest half-extent; 1 unit ~58 mm on the phantom face). Group offsets are divided
        by the radius before the shared MLP.
    group_size : per level, points per ball group (padded with the nearest when fewer)
    sa_widths : per level, widths of the set-abstraction shared MLP
    fp_widths : per feature-propagation module, *coarsest first* (``fp_widths[0]`` reads the
        last level and its skip), widths of the unit PointNet
    head_width : width of the unit PointNet layer before the output layer
    batch_norm : batch normalisation after every hidden layer (PointNet++'s choice)
    dropout : dropout probability before the output layer
    hard_boundary : if True, :meth:`PointNet2.forward` needs a :class:`BoundaryTargets` and
        returns exactly its values at its masked nodes
    """

    in_channels: int = 9
    out_channels: int = 3
    centers: tuple[int | float, ...] = (0.25, 0.25, 0.25, 0.25)
    radii: tuple[float, ...] = (0.15, 0.3, 0.6, 1.2)
    group_size: tuple[int, ...] = (32, 32, 32, 32)
    sa_widths: tuple[tuple[int, ...], ...] = ((32, 32, 64), (64, 64, 128), (128, 128, 256), (256, 256, 512))
    fp_widths: tuple[tuple[int, ...], ...] = ((256, 256), (256, 256), (256, 128), (128, 128, 128))
    head_width: int = 128
    batch_norm: bool = True
    dropout: float = 0.0
    hard_boundary: bool = False

    def __post_init__(self):
        for name, depth in (("centers", 1), ("radii", 1), ("group_size", 1), ("sa_widths", 2), ("fp_widths", 2)):
            object.__setattr__(self, name, _tuple(getattr(self, name), depth))
        levels = len(self.sa_widths)
        lengths = {name: len(getattr(self, name)) for name in ("centers", "radii", "group_size", "fp_widths")}
        if levels < 1 or any(v != levels for v in lengths.values()):
            raise ValueError(f"PointNet2Config: every per-level field needs one entry per level; got "
                             f"sa_widths with {levels} and {lengths}")
        if self.in_channels < 1 or self.out_channels < 1 or self.head_width < 1:
            raise ValueError(f"PointNet2Config: in_channels={self.in_channels}, out_channels={self.out_channels} "
                             f"and head_width={self.head_width} must be >= 1")
        for c in self.centers:
            if isinstance(c, bool) or not (isinstance(c, int) and c >= 1 or isinstance(c, float) and 0 < c <= 1):
                raise ValueError(f"PointNet2Config: centers entries are counts (int >= 1) or fractions (float in "
                                 f"(0, 1]), got {c!r} in {self.centers}")
        if any(not r >= 0 for r in self.radii):
            raise ValueError(f"PointNet2Config: radii must be >= 0, got {self.radii}")
        if any(k < 1 for k in self.group_size):
            raise ValueError(f"PointNet2Config: group_size entries must be >= 1, got {self.group_size}")
        if any(not w or min(w) < 1 for w in self.sa_widths + self.fp_widths):
            raise ValueError(f"PointNet2Config: every MLP needs at least one width >= 1, got sa_widths="
                             f"{self.sa_widths}, fp_widths={self.fp_widths}")
        if not 0 <= self.dropout < 1:
            raise ValueError(f"PointNet2Config: dropout must be in [0, 1), got {self.dropout}")

    @classmethod
    def coarse(cls, **changes) -> PointNet2Config:
        """Defaults for ~800-node meshes (the ``coarse`` phantom): radii scaled with the node
        spacing (~1.7x the ~4,000-node defaults), so the groups stay ~2/3 full."""
        return cls(**{"radii": (0.25, 0.5, 1.0, 2.0), **changes})

    @property
    def n_levels(self) -> int:
        return len(self.sa_widths)

    def level_sizes(self, n_points: int) -> tuple[int, ...]:
        """Number of points of every level for a mesh of ``n_points`` nodes, level 0 first."""
        sizes = [n_points]
        for level, c in enumerate(self.centers, start=1):
            m = c if isinstance(c, int) else max(1, math.ceil(c * sizes[-1]))
            if m > sizes[-1]:
                raise ValueError(f"PointNet2Config: level {level} asks for {m} centres but level {level - 1} has "
                                 f"only {sizes[-1]} points (mesh of {n_points} nodes); use fractions, e.g. "
                                 f"centers=(0.25, 0.25, 0.25, 0.25)")
            sizes.append(m)
        return tuple(sizes)

    def to_dict(self) -> dict:
        """Plain JSON-able dict (lists for tuples); :meth:`from_dict` inverts it."""
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> PointNet2Config:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(data) - known)
        if unknown:
            raise ValueError(f"PointNet2Config: unknown fields {unknown}; expected a subset of {sorted(known)}")
        return cls(**data)
