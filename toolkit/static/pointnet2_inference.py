"""PointNet++ inference in numpy: the forward pass of :class:`~toolkit.static.pointnet2.PointNet2`
without torch.

A trained model directory holds its weights as numpy arrays (``weights.npz``, written by
:meth:`~toolkit.common.training.bundle.ModelBundle.save`), so a prediction on the CPU reads
them and runs the network here, without importing torch (what that import costs a command is in
the `import torch` rows of `benchmarks/results/predict_speed.csv`).
The batch normalisations are folded into the linear layers before them, as
:meth:`~toolkit.static.pointnet2.PointNet2.fold_batch_norm` does; the arithmetic is float32,
as the torch network's, so both give the same output to float32 rounding. The hierarchy of a
mesh comes as the arrays of a :class:`~toolkit.static.pointnet2.PointHierarchy`
(:class:`HierarchyArrays`): a training subject's are stored with the weights; another mesh's are
built with torch once (:meth:`HierarchyArrays.from_hierarchy`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from toolkit.static.pointnet2_config import PointNet2Config

__all__ = ["HierarchyArrays", "PointNet2Inference"]

#: ``torch.nn.BatchNorm1d``'s default epsilon, which the trained norms used
_BN_EPS = 1e-5
_FIELDS = ("groups", "offsets", "interp_index", "interp_weight")


@dataclass(frozen=True, eq=False)
class HierarchyArrays:
    """The parts of a point hierarchy the forward pass reads, as numpy arrays (level ``l - 1``
    at index ``l - 1``): ball ``groups`` ``(m_l, k_l)`` int64 and their ``offsets``
    ``(m_l, k_l, 3)`` float32 (normalised by the radius), ``interp_index`` / ``interp_weight``
    ``(m_{l-1}, 3)`` of the 3-NN interpolation back to the finer level; ``n_points`` the mesh's
    node count."""

    groups: tuple[np.ndarray, ...]
    offsets: tuple[np.ndarray, ...]
    interp_index: tuple[np.ndarray, ...]
    interp_weight: tuple[np.ndarray, ...]
    n_points: int

    @classmethod
    def from_state(cls, state: dict) -> HierarchyArrays:
        """From :meth:`PointHierarchy.state_dict` as numpy arrays (``"groups.0"``, ...)."""
        levels = int(np.asarray(state["radii"]).size)
        parts = {name: tuple(np.asarray(state[f"{name}.{i}"]) for i in range(levels)) for name in _FIELDS}
        return cls(**parts, n_points=int(np.asarray(state["xyz.0"]).shape[0]))

    @classmethod
    def from_hierarchy(cls, hierarchy) -> HierarchyArrays:
        """From a torch :class:`~toolkit.static.pointnet2.PointHierarchy`."""
        parts = {name: tuple(t.detach().cpu().numpy() for t in getattr(hierarchy, name)) for name in _FIELDS}
        return cls(**parts, n_points=hierarchy.n_points)


def _fold(state: dict, linears: list[str], norm: str | None) -> tuple[list[np.ndarray], np.ndarray]:
    """The weights ``(out, in)`` of ``linears`` (the first carries the bias) with the eval-mode
    batch norm ``norm`` folded in: ``s (W x + b) + t`` is one affine map."""
    weights = [np.asarray(state[f"{name}.weight"], np.float64) for name in linears]
    bias = np.asarray(state[f"{linears[0]}.bias"], np.float64)
    if norm is not None and f"{norm}.weight" in state:
        scale = np.asarray(state[f"{norm}.weight"], np.float64) / np.sqrt(
            np.asarray(state[f"{norm}.running_var"], np.float64) + _BN_EPS)
        shift = np.asarray(state[f"{norm}.bias"], np.float64) - np.asarray(state[f"{norm}.running_mean"]) * scale
        weights = [w * scale[:, None] for w in weights]
        bias = bias * scale + shift
    return [np.ascontiguousarray(w.T, np.float32) for w in weights], bias.astype(np.float32)


def _mlp(state: dict, prefix: str, layers: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """The folded ``(W^T, b)`` of the ``layers`` linear + norm-ReLU pairs of an ``_mlp``."""
    out = []
    for j in range(layers):
        (w,), b = _fold(state, [f"{prefix}.{2 * j}"], f"{prefix}.{2 * j + 1}.norm")
        out.append((w, b))
    return out


def _dense(x: np.ndarray, w: np.ndarray, b: np.ndarray | None = None, relu: bool = False) -> np.ndarray:
    """``x (..., in) @ w (in, out) + b`` as one matrix product, optionally rectified in place."""
    y = (x.reshape(-1, x.shape[-1]) @ w).reshape(*x.shape[:-1], w.shape[1])
    if b is not None:
        y += b
    return np.maximum(y, 0.0, out=y) if relu else y


class PointNet2Inference:
    """The forward pass of a trained :class:`~toolkit.static.pointnet2.PointNet2`, in numpy.

    Parameters
    ----------
    config : the network's :class:`~toolkit.static.pointnet2_config.PointNet2Config`
    state : its ``state_dict()`` as numpy arrays (eval mode: batch norms use their running
        statistics; dropout is off)
    """

    def __init__(self, config: PointNet2Config, state: dict):
        self.config = config
        try:
            self._sa = []
            for i, widths in enumerate(config.sa_widths):
                p = f"set_abstraction.{i}"
                (wf, wo), b = _fold(state, [f"{p}.feature", f"{p}.offset"], f"{p}.act.norm")
                self._sa.append((wf, b, wo, _mlp(state, f"{p}.mlp", len(widths) - 1)))
            self._fp = []
            for i, widths in enumerate(config.fp_widths):
                p = f"feature_propagation.{i}"
                (ws, wc), b = _fold(state, [f"{p}.skip", f"{p}.coarse"], f"{p}.act.norm")
                self._fp.append((wc, ws, b, _mlp(state, f"{p}.mlp", len(widths) - 1)))
            (w0,), b0 = _fold(state, ["head.0"], "head.1.norm")
            (w1,), b1 = _fold(state, ["head.3"], None)
        except KeyError as err:
            raise ValueError(f"PointNet2Inference: the weights have no {err}; they do not belong to a PointNet2 of "
                             f"this config") from None
        self._head = ((w0, b0), (w1, b1))
        if w0.shape[0] != config.fp_widths[-1][-1] or w1.shape[1] != config.out_channels:
            raise ValueError("PointNet2Inference: the head's weights do not fit the config's widths")

    def __call__(self, features: np.ndarray, hierarchy: HierarchyArrays, mask: np.ndarray | None = None,
                 values: np.ndarray | None = None) -> np.ndarray:
        """Output ``(B, n, out_channels)`` float32 for ``features (B, n, in_channels)``; with
        ``config.hard_boundary``, ``mask (B, n)`` bool and ``values (B, n, 3)`` give the output
        exactly where ``mask`` is set (:func:`~toolkit.static.pointnet2.enforce_boundary`)."""
        cfg = self.config
        x = np.asarray(features, np.float32)
        if x.ndim != 3 or x.shape[-1] != cfg.in_channels or x.shape[1] != hierarchy.n_points:
            raise ValueError(f"PointNet2Inference: features must be (B, n={hierarchy.n_points}, "
                             f"in_channels={cfg.in_channels}), got {x.shape}")
        if cfg.hard_boundary != (mask is not None and values is not None):
            raise ValueError(f"PointNet2Inference: hard_boundary={cfg.hard_boundary} needs mask and values "
                             "exactly when it is set")
        skips = [x]
        for (wf, bf, wo, mlp), groups, offsets in zip(self._sa, hierarchy.groups, hierarchy.offsets):
            h = _dense(x, wf, bf)[:, groups] + _dense(offsets, wo)
            np.maximum(h, 0.0, out=h)
            for w, b in mlp:
                h = _dense(h, w, b, relu=True)
            x = h.max(axis=2)
            skips.append(x)
        levels = range(cfg.n_levels - 1, -1, -1)
        for level, (wc, ws, b, mlp) in zip(levels, self._fp):
            coarse = _dense(x, wc)
            index, weight = hierarchy.interp_index[level], hierarchy.interp_weight[level].astype(np.float32)
            h = np.einsum("bnkc,nk->bnc", coarse[:, index], weight) + _dense(skips[level], ws, b)
            np.maximum(h, 0.0, out=h)
            for w, bb in mlp:
                h = _dense(h, w, bb, relu=True)
            x = h
        (w0, b0), (w1, b1) = self._head
        out = _dense(_dense(x, w0, b0, relu=True), w1, b1)
        if mask is not None:
            out = np.where(np.asarray(mask, bool)[..., None], np.asarray(values, np.float32), out)
        return out
