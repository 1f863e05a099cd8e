"""PointNet++ for nodal displacement on a face mesh (the PointNet++ paper), in plain PyTorch.

Three layers, each usable on its own:

1. **Neighbourhood operations** on point clouds, vectorised over batch and points:
   :func:`farthest_point_sampling`, :func:`ball_query`, :func:`three_nn` and
   :func:`three_nn_interpolate`.
2. **A point hierarchy per mesh** (:class:`PointHierarchy`): the sampled centres, ball
   groups and 3-NN interpolation weights of every level, computed once from the mesh's
   reference coordinates and shared by every sample on that mesh, so a forward pass does no
   neighbour search. It is plain tensors: save it with the model (:meth:`~PointHierarchy.state_dict`)
   and move it with :meth:`~PointHierarchy.to`.
3. **The network** (:class:`PointNet2`): set-abstraction modules (shared MLP on
   ``[offset, features]`` of each group, max pool) and feature-propagation modules (3-NN
   interpolation, unit PointNet on ``[interpolated, skip]``), then a head giving a 3-vector
   per node; with ``hard_boundary`` the output is exactly the prescribed value at
   constrained nodes (:class:`BoundaryTargets`, :func:`enforce_boundary`).

Typical use (``points`` the mesh's reference coordinates, ``features`` built by the caller)::

    config = PointNet2Config(in_channels=9)            # coords 3 + one-hot 3 + s 3
    hierarchy = PointHierarchy.build(points, config)   # once per mesh; (n, 3) mm
    model = PointNet2(config)
    u = model(features, hierarchy)                     # (B, n, 9) -> (B, n, 3)

    # hard boundary conditions: exactly 0 at fixed nodes, exactly s at moving nodes
    config = PointNet2Config(in_channels=9, hard_boundary=True)
    u = PointNet2(config)(features, hierarchy, BoundaryTargets.from_types(types, s))

    # one file for config, weights and hierarchy (plain tensors, ``weights_only=True`` loads it)
    torch.save({"config": config.to_dict(), "model": model.state_dict(),
                "hierarchy": hierarchy.state_dict()}, path)
    saved = torch.load(path, weights_only=True)
    model = PointNet2(PointNet2Config.from_dict(saved["config"]), device="cuda")
    model.load_state_dict(saved["model"])
    hierarchy = PointHierarchy.from_state_dict(saved["hierarchy"], device="cuda")

Geometry is normalised before any distance: coordinates are centred on their bounding box
and divided by its largest half-extent, so the mesh fits in ``[-1, 1]^3`` and radii are in
those units (1 unit is ~58 mm on the phantom face). Hierarchies are permutation-equivariant:
building one on the nodes in another order gives the same centres and groups, re-indexed
(ties between equal distances are broken by the points' lexicographic order, not by their
index), so permuting the input nodes permutes the output. The one exception is coincident
nodes (the two faces of the closed mouth slit): which copy a group holds when the group's
size cuts between them follows the input order. Coincident nodes are geometrically one
point to the network; only their input features can tell them apart
(:attr:`PointHierarchy.n_coincident` counts them).
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor, nn

from toolkit.static.boundary import NodeType
from toolkit.static.pointnet2_config import PointNet2Config

__all__ = [
    "farthest_point_sampling",
    "ball_query",
    "three_nn",
    "three_nn_interpolate",
    "PointNet2Config",
    "PointHierarchy",
    "PointNet2",
    "BoundaryTargets",
    "enforce_boundary",
]

#: elements of one pairwise-distance block (queries x references); bounds memory at ~100 MB
_BLOCK = 1 << 22
#: squared distance (normalised units) under which two points count as coincident
_COINCIDENT = 1e-12


# ----------------------------------------------------------------------------------------------
# Neighbourhood operations
# ----------------------------------------------------------------------------------------------

def _check_points(name: str, xyz: Tensor) -> None:
    if xyz.dim() < 2 or xyz.shape[-1] != 3:
        raise ValueError(f"{name} must have shape (..., n, 3), got {tuple(xyz.shape)}")


def _square_distance(query: Tensor, ref: Tensor) -> Tensor:
    """Squared distances ``(..., n, m)`` from squared coordinate differences (exactly 0 for
    coincident points, never negative; no ``|a|^2 + |b|^2 - 2ab`` cancellation)."""
    d2 = (query[..., :, None, 0] - ref[..., None, :, 0]) ** 2
    for i in (1, 2):
        d2 += (query[..., :, None, i] - ref[..., None, :, i]) ** 2
    return d2


def _nearest(query: Tensor, ref: Tensor, k: int) -> tuple[Tensor, Tensor]:
    """The ``k`` nearest ``ref`` points of every query point, nearest first.

    query : (..., n, 3); ref : (..., m, 3) with the same leading shape; ``k <= m``.
    Returns squared distances ``(..., n, k)`` and indices into ``ref`` ``(..., n, k)`` int64.
    Equal distances are ordered by index, so the result is a deterministic function of the
    coordinates and of ref's order: ``topk`` of ``k + 1`` (its tie order is unspecified) is
    re-ordered by (distance, index), and rows where the ``k``-th and ``k+1``-th distances tie
    fall back to a stable sort. Queries are processed in blocks to bound memory.
    """
    n, m = query.shape[-2], ref.shape[-2]
    step = max(1, _BLOCK // max(1, m))
    d2_out, idx_out = [], []
    for lo in range(0, n, step):
        d2 = _square_distance(query[..., lo:lo + step, :], ref)
        if k < m:
            val, idx = torch.topk(d2, k + 1, dim=-1, largest=False, sorted=True)
            tie = val[..., k - 1] == val[..., k]
            val, idx = val[..., :k], idx[..., :k]
            idx, perm = idx.sort(dim=-1)
            val, perm = val.gather(-1, perm).sort(dim=-1, stable=True)
            idx = idx.gather(-1, perm)
            if tie.any():
                full_val, full_idx = torch.sort(d2[tie], dim=-1, stable=True)
                val[tie], idx[tie] = full_val[..., :k], full_idx[..., :k]
        else:
            val, idx = torch.sort(d2, dim=-1, stable=True)
        d2_out.append(val)
        idx_out.append(idx)
    return torch.cat(d2_out, dim=-2), torch.cat(idx_out, dim=-2)


def farthest_point_sampling(xyz: Tensor, m: int, start: int | Tensor = 0) -> Tensor:
    """Indices of ``m`` points chosen by farthest point sampling from a fixed start.

    Each new point maximises the distance to the points already chosen (ties: lowest
    index), so the result is deterministic. The loop runs over the ``m`` samples (the method
    is sequential); every step is vectorised over batch and points.

    Parameters
    ----------
    xyz : (..., n, 3) float — coordinates, any length unit (normalise first for meshes)
    m : int — number of samples, ``1 <= m <= n``
    start : int or (...,) int64 tensor — index of the first sample (per batch entry)

    Returns
    -------
    (..., m) int64 — indices into the ``n`` points, ``start`` first
    """
    _check_points("xyz", xyz)
    n = xyz.shape[-2]
    if not 1 <= m <= n:
        raise ValueError(f"farthest_point_sampling: m={m} samples requested from n={n} points; expected 1 <= m <= n")
    batch_shape = xyz.shape[:-2]
    x = xyz.reshape(-1, n, 3)
    b = x.shape[0]
    rows = torch.arange(b, device=xyz.device)
    current = torch.as_tensor(start, dtype=torch.long, device=xyz.device).expand(batch_shape).reshape(-1).clone()
    if current.numel() and (current.min() < 0 or current.max() >= n):
        raise ValueError(f"farthest_point_sampling: start index {start} out of range for n={n} points")
    chosen = torch.empty(b, m, dtype=torch.long, device=xyz.device)
    dist = torch.full((b, n), math.inf, dtype=xyz.dtype, device=xyz.device)
    for i in range(m):
        chosen[:, i] = current
        d2 = _square_distance(x[rows, current].unsqueeze(1), x).squeeze(1)
        dist = torch.minimum(dist, d2)
        current = dist.argmax(dim=-1)  # first maximal index on ties (documented torch behaviour)
    return chosen.reshape(*batch_shape, m)


def ball_query(xyz: Tensor, centers: Tensor, radius: float, k: int) -> Tensor:
    """Up to ``k`` points within ``radius`` of each centre, nearest first; never out of range.

    Groups with fewer than ``k`` points inside the ball (also ``radius = 0`` or fewer than
    ``k`` points in all) are padded with the first neighbour found, the nearest point. A
    centre that is one of the points always finds itself; a centre whose ball is empty gets
    its nearest point ``k`` times.

    Parameters
    ----------
    xyz : (..., n, 3) float — points, same unit as ``radius``
    centers : (..., m, 3) float — ball centres, same leading shape as ``xyz``
    radius : float >= 0
    k : int >= 1 — group size

    Returns
    -------
    (..., m, k) int64 — indices into the ``n`` points, each in ``[0, n)``
    """
    _check_points("xyz", xyz)
    _check_points("centers", centers)
    if not radius >= 0:
        raise ValueError(f"ball_query: radius must be >= 0, got {radius}")
    if k < 1:
        raise ValueError(f"ball_query: group size k must be >= 1, got {k}")
    n = xyz.shape[-2]
    if n == 0:
        raise ValueError("ball_query: xyz holds no points")
    d2, idx = _nearest(centers, xyz, min(k, n))
    idx = torch.where(d2 <= radius * radius, idx, idx[..., :1])
    if idx.shape[-1] < k:
        idx = torch.cat([idx, idx[..., :1].expand(*idx.shape[:-1], k - idx.shape[-1])], dim=-1)
    return idx


def three_nn(xyz: Tensor, ref: Tensor, eps: float = _COINCIDENT) -> tuple[Tensor, Tensor]:
    """Three nearest ``ref`` points of every point and their inverse-distance weights.

    Weights are ``1 / d^2`` (PointNet++'s ``p = 2``), normalised to sum to 1; a point closer
    than ``sqrt(eps)`` to its nearest reference takes that reference's value exactly
    (weights ``[1, 0, 0]``). With fewer than 3 references the missing neighbours repeat the
    nearest with weight 0.

    Parameters
    ----------
    xyz : (..., n, 3) float — points to interpolate at
    ref : (..., m, 3) float — points carrying values, same leading shape, ``m >= 1``
    eps : float — squared-distance guard, in the coordinates' unit squared

    Returns
    -------
    index : (..., n, 3) int64 — into the ``m`` references, nearest first
    weight : (..., n, 3) float — non-negative, summing to 1 over the last axis
    """
    _check_points("xyz", xyz)
    _check_points("ref", ref)
    m = ref.shape[-2]
    if m == 0:
        raise ValueError("three_nn: ref holds no points")
    d2, idx = _nearest(xyz, ref, min(3, m))
    weight = 1.0 / d2.clamp_min(eps)
    coincident = d2[..., :1] <= eps
    first = torch.zeros_like(weight)
    first[..., 0] = 1.0
    weight = torch.where(coincident, first, weight)
    weight = weight / weight.sum(-1, keepdim=True)
    if idx.shape[-1] < 3:
        pad = 3 - idx.shape[-1]
        idx = torch.cat([idx, idx[..., :1].expand(*idx.shape[:-1], pad)], dim=-1)
        weight = torch.cat([weight, weight.new_zeros(*weight.shape[:-1], pad)], dim=-1)
    return idx, weight


def three_nn_interpolate(features: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """Interpolate features from references to points with :func:`three_nn`'s result.

    features : (B, m, C) float — values at the references
    index, weight : (n, 3) shared by the batch, or (B, n, 3) per sample

    Returns ``(B, n, C)``: ``sum_j weight[..., j] * features[index[..., j]]``.
    """
    if features.dim() != 3:
        raise ValueError(f"three_nn_interpolate: features must be (B, m, C), got {tuple(features.shape)}")
    if index.shape != weight.shape or index.shape[-1] != 3 or index.dim() not in (2, 3):
        raise ValueError(f"three_nn_interpolate: index and weight must both be (n, 3) or (B, n, 3), got "
                         f"{tuple(index.shape)} and {tuple(weight.shape)}")
    if index.dim() == 3 and index.shape[0] != features.shape[0]:
        raise ValueError(f"three_nn_interpolate: per-sample index for batch {index.shape[0]} but features "
                         f"have batch {features.shape[0]}")
    w = weight.to(features.dtype).unsqueeze(-1)
    if index.dim() == 2:
        return (features[:, index] * w).sum(-2)
    b = torch.arange(features.shape[0], device=features.device).view(-1, 1, 1)
    return (features[b, index] * w).sum(-2)


# ----------------------------------------------------------------------------------------------
# The hierarchy of one mesh
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class PointHierarchy:
    """Sampled centres, ball groups and interpolation weights of one mesh, every level.

    Build with :meth:`build`; all samples on the mesh share it. Level 0 is the mesh's nodes in
    the caller's order, level ``l`` the centres sampled from level ``l - 1``. Lists below are
    indexed by ``l - 1`` for levels ``l = 1..L``.

    Attributes
    ----------
    xyz : L+1 tensors ``(m_l, 3)`` float32 — normalised coordinates of every level
    sample : L tensors ``(m_l,)`` int64 — centres of level ``l`` as indices into level ``l - 1``
    groups : L tensors ``(m_l, k_l)`` int64 — ball group of each centre, indices into level ``l - 1``
    offsets : L tensors ``(m_l, k_l, 3)`` float32 — group points minus centre, divided by the radius
    interp_index : L tensors ``(m_{l-1}, 3)`` int64 — 3 nearest level-``l`` centres of each level-``l-1`` point
    interp_weight : L tensors ``(m_{l-1}, 3)`` float32 — their inverse-squared-distance weights (sum 1)
    radii : tuple of float — ball radius per level, normalised units
    center : (3,) float64, mm — bounding-box centre subtracted from the coordinates
    scale : float, mm — largest bounding-box half-extent the coordinates were divided by
    """

    xyz: tuple[Tensor, ...]
    sample: tuple[Tensor, ...]
    groups: tuple[Tensor, ...]
    offsets: tuple[Tensor, ...]
    interp_index: tuple[Tensor, ...]
    interp_weight: tuple[Tensor, ...]
    radii: tuple[float, ...]
    center: Tensor
    scale: float

    def __post_init__(self):
        levels = len(self.sample)
        for name in ("groups", "offsets", "interp_index", "interp_weight"):
            if len(getattr(self, name)) != levels:
                raise ValueError(f"PointHierarchy: {name} has {len(getattr(self, name))} levels, sample has {levels}")
        if len(self.xyz) != levels + 1 or len(self.radii) != levels:
            raise ValueError(f"PointHierarchy: expected {levels + 1} coordinate levels and {levels} radii, got "
                             f"{len(self.xyz)} and {len(self.radii)}")
        for name in ("xyz", "sample", "groups", "offsets", "interp_index", "interp_weight"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        object.__setattr__(self, "radii", tuple(float(r) for r in self.radii))
        object.__setattr__(self, "scale", float(self.scale))

    # -- construction ------------------------------------------------------------------------
    @classmethod
    def build(cls, points, config: PointNet2Config, device: str | torch.device | None = None) -> PointHierarchy:
        """Hierarchy of a mesh for ``config``'s levels, radii and group sizes.

        Parameters
        ----------
        points : (n, 3) float, mm — reference coordinates of the mesh nodes (numpy or tensor);
            computed in float64 on the CPU
        config : :class:`PointNet2Config`
        device : where to put the result (default CPU)

        The first centre of every level is the point nearest the bounding-box centre, and
        equal distances are ordered by the points' lexicographic order, so the hierarchy of a
        permuted mesh is this one re-indexed.
        """
        p = torch.from_numpy(np.array(points.detach().cpu() if isinstance(points, Tensor) else points,
                                      dtype=np.float64))
        if p.dim() != 2 or p.shape[1] != 3 or p.shape[0] < 1:
            raise ValueError(f"PointHierarchy.build: points must be (n, 3) with n >= 1, got {tuple(p.shape)}")
        if not torch.isfinite(p).all():
            bad = torch.nonzero(~torch.isfinite(p).all(1)).flatten()
            raise ValueError(f"PointHierarchy.build: {bad.numel()} points are not finite (first: {bad[:5].tolist()})")
        sizes = config.level_sizes(p.shape[0])
        lo, hi = p.min(0).values, p.max(0).values
        center = (lo + hi) / 2
        scale = float((hi - lo).max()) / 2 or 1.0
        x = (p - center) / scale

        xyz, sample, groups, offsets, index, weight = [x], [], [], [], [], []
        # canonical (lexicographic) order of the level being sampled; deeper levels are in FPS
        # order, which is already independent of the input order
        order = torch.from_numpy(np.lexsort(x.numpy().T[::-1]).copy())
        for m, radius, k in zip(sizes[1:], config.radii, config.group_size):
            cur = xyz[-1]
            canon = cur[order]
            start = int((canon ** 2).sum(1).argmin())
            picked = order[farthest_point_sampling(canon, m, start)]
            centers = cur[picked]
            group = order[ball_query(canon, centers, radius, k)]
            idx, w = three_nn(cur, centers)
            sample.append(picked)
            groups.append(group)
            offsets.append(((cur[group] - centers.unsqueeze(1)) / (radius if radius > 0 else 1.0)).float())
            index.append(idx)
            weight.append(w.float())
            xyz.append(centers)
            order = torch.arange(m)
        hierarchy = cls(tuple(t.float() for t in xyz), tuple(sample), tuple(groups), tuple(offsets), tuple(index),
                        tuple(weight), config.radii, center, scale)
        return hierarchy if device is None else hierarchy.to(device)

    # -- facts -------------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        """Nodes of the mesh (level 0)."""
        return self.xyz[0].shape[0]

    @property
    def n_levels(self) -> int:
        return len(self.sample)

    @property
    def sizes(self) -> tuple[int, ...]:
        """Points per level, level 0 first."""
        return tuple(t.shape[0] for t in self.xyz)

    @property
    def group_size(self) -> tuple[int, ...]:
        return tuple(g.shape[1] for g in self.groups)

    @property
    def device(self) -> torch.device:
        return self.xyz[0].device

    @property
    def n_coincident(self) -> int:
        """Nodes that share their coordinates with another node (e.g. the closed mouth slit):
        the network tells them apart only through their input features."""
        return self.n_points - torch.unique(self.xyz[0], dim=0).shape[0]

    def fingerprint(self) -> str:
        """SHA-1 of the normalised coordinates, normalisation and neighbourhoods: equal for
        hierarchies built from the same nodes (same order) with the same settings."""
        h = hashlib.sha1()
        for t in (*self.xyz, *self.groups, self.center, torch.tensor(self.radii + (self.scale,))):
            h.update(t.detach().cpu().contiguous().numpy().tobytes())
        return h.hexdigest()

    # -- transforms --------------------------------------------------------------------------
    def to(self, device: str | torch.device) -> PointHierarchy:
        """Copy on ``device`` (``center`` stays a CPU float64 tensor)."""
        move = lambda ts: tuple(t.to(device) for t in ts)  # noqa: E731
        return PointHierarchy(move(self.xyz), move(self.sample), move(self.groups), move(self.offsets),
                              move(self.interp_index), move(self.interp_weight), self.radii, self.center, self.scale)

    def state_dict(self) -> dict[str, Tensor]:
        """Plain CPU tensors (``torch.save``-able, loadable with ``weights_only=True``)."""
        state = {"radii": torch.tensor(self.radii, dtype=torch.float64), "center": self.center.cpu(),
                 "scale": torch.tensor(self.scale, dtype=torch.float64)}
        for name in ("xyz", "sample", "groups", "offsets", "interp_index", "interp_weight"):
            for i, t in enumerate(getattr(self, name)):
                state[f"{name}.{i}"] = t.detach().cpu()
        return state

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor], device: str | torch.device | None = None) -> PointHierarchy:
        """Inverse of :meth:`state_dict`."""
        try:
            levels = state["radii"].numel()
            parts = {name: tuple(state[f"{name}.{i}"] for i in range(levels + (name == "xyz")))
                     for name in ("xyz", "sample", "groups", "offsets", "interp_index", "interp_weight")}
            hierarchy = cls(**parts, radii=tuple(state["radii"].tolist()), center=state["center"],
                            scale=float(state["scale"]))
        except KeyError as err:
            raise ValueError(f"PointHierarchy.from_state_dict: missing entry {err}; was this saved by "
                             f"PointHierarchy.state_dict()?") from None
        return hierarchy if device is None else hierarchy.to(device)


# ----------------------------------------------------------------------------------------------
# Hard boundary conditions
# ----------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)
class BoundaryTargets:
    """Values the output must take exactly at some nodes (hard boundary conditions).

    Attributes
    ----------
    mask : bool tensor — where the output is prescribed: ``(n,)`` per node for the whole
        batch, ``(B, n)`` per node and sample, or ``(B, n, 3)`` / ``(1, n, 3)`` per component
        (e.g. for a caller's sliding-node treatment)
    values : float tensor ``(n, 3)`` or ``(B, n, 3)`` — the prescribed outputs, in the unit of
        the network's output (mm, or the targets' unit if the caller scales them; scale by a
        factor, not a shift, or fixed nodes stop being 0). Read only where ``mask`` is True.
    """

    mask: Tensor
    values: Tensor

    def __post_init__(self):
        mask = torch.as_tensor(self.mask)
        values = torch.as_tensor(self.values)
        if mask.dtype != torch.bool:
            raise TypeError(f"BoundaryTargets: mask must be a bool tensor, got {mask.dtype}")
        if mask.dim() not in (1, 2, 3) or (mask.dim() == 3 and mask.shape[-1] != 3):
            raise ValueError(f"BoundaryTargets: mask must be (n,), (B, n) or (B, n, 3), got {tuple(mask.shape)}")
        if values.dim() not in (2, 3) or values.shape[-1] != 3 or not values.is_floating_point():
            raise ValueError(f"BoundaryTargets: values must be float (n, 3) or (B, n, 3), got "
                             f"{tuple(values.shape)} {values.dtype}")
        n_mask = mask.shape[0] if mask.dim() == 1 else mask.shape[1]
        if n_mask != values.shape[-2]:
            raise ValueError(f"BoundaryTargets: mask covers {n_mask} nodes but values {values.shape[-2]}")
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "values", values)

    @classmethod
    def from_types(cls, types, prescribed: Tensor) -> BoundaryTargets:
        """The PointNet++ paper's boundary types: fixed nodes -> 0, moving nodes -> their prescribed ``s``.

        types : (n,) int — :class:`~toolkit.static.boundary.NodeType` codes (free 0, moving 1,
            fixed 2, mucosa 3, lip 4); sliding and free nodes stay free
        prescribed : (n, 3) or (B, n, 3) float — prescribed displacement ``s``, output unit
        """
        t = torch.as_tensor(np.asarray(types.cpu() if isinstance(types, Tensor) else types, dtype=np.int64))
        prescribed = torch.as_tensor(prescribed)
        t = t.to(prescribed.device)
        moving, fixed = t == NodeType.MOVING, t == NodeType.FIXED
        values = torch.where(fixed.unsqueeze(-1), torch.zeros((), dtype=prescribed.dtype, device=prescribed.device),
                             prescribed)
        return cls(moving | fixed, values)

    def to(self, device: str | torch.device) -> BoundaryTargets:
        return BoundaryTargets(self.mask.to(device), self.values.to(device))


def enforce_boundary(output: Tensor, boundary: BoundaryTargets) -> Tensor:
    """``output`` with ``boundary.values`` where ``boundary.mask`` is set, exactly.

    output : (B, n, 3) float; returns the same shape. Gradients reach the network output only
    at the free entries.
    """
    b, n = output.shape[0], output.shape[1]
    mask, values = boundary.mask.to(output.device), boundary.values.to(output.device, output.dtype)
    mask = {1: lambda: mask[None, :, None], 2: lambda: mask[:, :, None], 3: lambda: mask}[mask.dim()]()
    if values.dim() == 2:
        values = values.unsqueeze(0)
    for name, t in (("mask", mask), ("values", values)):
        if t.shape[1] != n or t.shape[0] not in (1, b):
            raise ValueError(f"enforce_boundary: {name} of shape {tuple(t.shape)} does not fit an output of "
                             f"{b} samples x {n} nodes")
    return torch.where(mask, values, output)


# ----------------------------------------------------------------------------------------------
# The network
# ----------------------------------------------------------------------------------------------

class _NormAct(nn.Module):
    """Batch norm over every entry of a channels-last tensor (optional), then ReLU."""

    def __init__(self, channels: int, batch_norm: bool):
        super().__init__()
        self.norm = nn.BatchNorm1d(channels) if batch_norm else None

    def forward(self, x: Tensor) -> Tensor:
        if self.norm is not None:
            x = self.norm(x.reshape(-1, x.shape[-1])).reshape(x.shape)
        # x is always a fresh layer output here, so without autograd it may be overwritten
        return torch.relu(x) if torch.is_grad_enabled() else torch.relu_(x)


def _mlp(in_channels: int, widths: tuple[int, ...], batch_norm: bool) -> nn.Sequential:
    layers = []
    for w in widths:
        layers += [nn.Linear(in_channels, w), _NormAct(w, batch_norm)]
        in_channels = w
    return nn.Sequential(*layers)


def _mlp_pairs(mlp: nn.Sequential) -> list:
    """``((linear,), norm-act)`` of every layer of an :func:`_mlp`."""
    return [((mlp[i],), mlp[i + 1]) for i in range(0, len(mlp), 2)]


class SetAbstraction(nn.Module):
    """Sampling + grouping + PointNet: a shared MLP on ``[offset, features]`` of every group
    point, max-pooled over the group.

    The first layer is split as ``W_o offset + W_f features``, and ``W_f`` is applied to the
    points before grouping (each point enters ~``k`` groups): the same function, fewer products.
    """

    def __init__(self, in_channels: int, widths: tuple[int, ...], batch_norm: bool):
        super().__init__()
        self.feature = nn.Linear(in_channels, widths[0])
        self.offset = nn.Linear(3, widths[0], bias=False)
        self.act = _NormAct(widths[0], batch_norm)
        self.mlp = _mlp(widths[0], widths[1:], batch_norm)

    def forward(self, features: Tensor, groups: Tensor, offsets: Tensor) -> Tensor:
        """features (B, n, C), groups (m, k), offsets (m, k, 3) -> (B, m, widths[-1])"""
        h = self.feature(features)[:, groups] + self.offset(offsets)
        return self.mlp(self.act(h)).amax(dim=2)


class FeaturePropagation(nn.Module):
    """3-NN interpolation of the coarse features + unit PointNet on ``[interpolated, skip]``.

    The first layer's coarse half is applied before interpolating (interpolation is linear),
    on the fewer coarse points.
    """

    def __init__(self, coarse_channels: int, skip_channels: int, widths: tuple[int, ...], batch_norm: bool):
        super().__init__()
        self.coarse = nn.Linear(coarse_channels, widths[0], bias=False)
        self.skip = nn.Linear(skip_channels, widths[0])
        self.act = _NormAct(widths[0], batch_norm)
        self.mlp = _mlp(widths[0], widths[1:], batch_norm)

    def forward(self, coarse: Tensor, skip: Tensor, index: Tensor, weight: Tensor) -> Tensor:
        """coarse (B, m, C1), skip (B, n, C2), index/weight (n, 3) -> (B, n, widths[-1])"""
        h = three_nn_interpolate(self.coarse(coarse), index, weight) + self.skip(skip)
        return self.mlp(self.act(h))


class PointNet2(nn.Module):
    """PointNet++ regression of a vector per node (the PointNet++ paper): L set-abstraction modules,
    L feature-propagation modules with skip connections, a unit-PointNet head.

    Parameters
    ----------
    config : :class:`PointNet2Config`
    device : optional device for the parameters (float32)

    The weights do not depend on the mesh: one model runs on any mesh whose
    :class:`PointHierarchy` was built with the same config (several subjects, one model).
    """

    def __init__(self, config: PointNet2Config | None = None, device: str | torch.device | None = None):
        super().__init__()
        self.config = config = config or PointNet2Config()
        sa, channels = [], [config.in_channels]
        for widths in config.sa_widths:
            sa.append(SetAbstraction(channels[-1], widths, config.batch_norm))
            channels.append(widths[-1])
        fp, coarse = [], channels[-1]
        for level, widths in zip(range(config.n_levels - 1, -1, -1), config.fp_widths):
            fp.append(FeaturePropagation(coarse, channels[level], widths, config.batch_norm))
            coarse = widths[-1]
        self.set_abstraction = nn.ModuleList(sa)
        self.feature_propagation = nn.ModuleList(fp)
        self.head = nn.Sequential(nn.Linear(coarse, config.head_width), _NormAct(config.head_width, config.batch_norm),
                                  nn.Dropout(config.dropout), nn.Linear(config.head_width, config.out_channels))
        if device is not None:
            self.to(device)

    def forward(self, features: Tensor, hierarchy: PointHierarchy, boundary: BoundaryTargets | None = None) -> Tensor:
        """Output per node.

        Parameters
        ----------
        features : (B, n, in_channels) float — node features in the mesh's node order (cast to
            the parameters' dtype); e.g. ``[coordinates, one-hot, s]`` scaled to [0, 1]
        hierarchy : :class:`PointHierarchy` of the mesh, on the same device
        boundary : :class:`BoundaryTargets`, required when ``config.hard_boundary`` (and only then)

        Returns
        -------
        (B, n, out_channels) float — e.g. displacement in the training targets' unit
        """
        self._check(features, hierarchy, boundary)
        x = features.to(self.head[-1].weight.dtype)
        skips = [x]
        for sa, groups, offsets in zip(self.set_abstraction, hierarchy.groups, hierarchy.offsets):
            x = sa(x, groups, offsets)
            skips.append(x)
        for level, fp in zip(range(self.config.n_levels - 1, -1, -1), self.feature_propagation):
            x = fp(x, skips[level], hierarchy.interp_index[level], hierarchy.interp_weight[level])
        out = self.head(x)
        return enforce_boundary(out, boundary) if boundary is not None else out

    def fold_batch_norm(self) -> PointNet2:
        """An inference copy with every batch normalisation folded into the linear layers before
        it (in eval mode a batch norm is the affine map ``s x + t`` per channel, so ``s (W x + b)
        + t`` is one linear layer). Same outputs up to rounding, fewer operations per call; the
        copy is in eval mode and is not for training (its norms are gone)."""
        import copy

        folded = copy.deepcopy(self).eval()
        pairs = []
        for sa in folded.set_abstraction:
            pairs += [((sa.feature, sa.offset), sa.act), *_mlp_pairs(sa.mlp)]
        for fp in folded.feature_propagation:
            pairs += [((fp.skip, fp.coarse), fp.act), *_mlp_pairs(fp.mlp)]
        pairs.append(((folded.head[0],), folded.head[1]))
        with torch.no_grad():
            for linears, act in pairs:
                if act.norm is None:
                    continue
                bn = act.norm
                scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
                shift = bn.bias - bn.running_mean * scale
                for k, linear in enumerate(linears):
                    linear.weight.mul_(scale[:, None])
                    if k == 0:  # the first carries the bias
                        linear.bias.mul_(scale).add_(shift)
                act.norm = None
        return folded

    def _check(self, features: Tensor, hierarchy: PointHierarchy, boundary: BoundaryTargets | None) -> None:
        cfg = self.config
        if features.dim() != 3 or features.shape[-1] != cfg.in_channels:
            raise ValueError(f"PointNet2: features must be (B, n, in_channels={cfg.in_channels}), got "
                             f"{tuple(features.shape)}")
        if features.shape[1] != hierarchy.n_points:
            raise ValueError(f"PointNet2: features have {features.shape[1]} nodes but the hierarchy was built for a "
                             f"mesh of {hierarchy.n_points}; build one with PointHierarchy.build(points, config)")
        if (hierarchy.n_levels != cfg.n_levels or hierarchy.radii != tuple(map(float, cfg.radii))
                or hierarchy.group_size != cfg.group_size):
            raise ValueError(f"PointNet2: hierarchy has {hierarchy.n_levels} levels, radii {hierarchy.radii}, groups "
                             f"{hierarchy.group_size}; the config expects {cfg.n_levels}, {cfg.radii}, "
                             f"{cfg.group_size}: build it with this model's config")
        if hierarchy.device != features.device:
            raise ValueError(f"PointNet2: features on {features.device} but hierarchy on {hierarchy.device}; "
                             f"use hierarchy.to({str(features.device)!r})")
        if cfg.hard_boundary and boundary is None:
            raise ValueError("PointNet2: config.hard_boundary is set, so forward() needs boundary=BoundaryTargets(...)")
        if not cfg.hard_boundary and boundary is not None:
            raise ValueError("PointNet2: a boundary was given but config.hard_boundary is False; set it in the config "
                             "(or call enforce_boundary on the output yourself)")
