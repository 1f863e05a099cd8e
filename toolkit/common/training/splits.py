"""Train/validation/test splits that keep groups whole.

A *group* is whatever must not straddle two splits: a simulation (all its nodes and
frames), a subject, a surgical plan. :func:`split_groups` shuffles the distinct group
labels with a seed and deals them to the splits by the requested fractions of
*groups*; every item follows its group. With one item per group it is the usual
random item split.
"""

from __future__ import annotations

import numpy as np

from toolkit.common.training.seeding import check_seed

__all__ = ["split_groups", "group_counts"]


def group_counts(n_groups: int, fractions) -> np.ndarray:
    """How many of ``n_groups`` go to each split: largest-remainder rounding of
    ``fractions * n_groups``, with at least one group for every positive fraction when there
    are enough groups. ``(k,)`` int64 summing to ``n_groups``."""
    f = np.asarray(fractions, dtype=float)
    if f.ndim != 1 or f.size == 0 or not np.isfinite(f).all() or (f < 0).any() or not np.isclose(f.sum(), 1.0):
        raise ValueError(f"fractions must be non-negative and sum to 1, got {list(np.atleast_1d(f))}")
    positive = f > 0
    if n_groups < positive.sum():
        raise ValueError(f"{n_groups} group(s) cannot fill {int(positive.sum())} non-empty splits {f.tolist()}")
    exact = f * n_groups
    counts = np.floor(exact).astype(np.int64)
    order = np.argsort(-(exact - counts), kind="stable")
    counts[order[: n_groups - counts.sum()]] += 1
    for i in np.flatnonzero(positive & (counts == 0)):  # give an empty split one group from the largest
        j = int(np.argmax(counts))
        counts[j] -= 1
        counts[i] += 1
    return counts


def split_groups(groups, fractions, seed: int) -> tuple[np.ndarray, ...]:
    """Split items by group.

    Parameters
    ----------
    groups : (n_items,) group label of each item (any sortable dtype)
    fractions : (k,) fractions of *groups* per split, summing to 1 (e.g. ``(0.7, 0.1, 0.2)``)
    seed : the shuffle's seed

    Returns
    -------
    k arrays of item indices (int64, ascending); together a partition of ``range(n_items)``
    in which no group appears in two arrays.
    """
    seed = check_seed(seed)
    g = np.asarray(groups)
    if g.ndim != 1 or g.size == 0:
        raise ValueError(f"groups must be a non-empty 1-D array of labels, got shape {g.shape}")
    labels, inverse = np.unique(g, return_inverse=True)
    counts = group_counts(labels.size, fractions)
    perm = np.random.default_rng(seed).permutation(labels.size)
    which = np.empty(labels.size, dtype=np.int64)
    which[perm] = np.repeat(np.arange(counts.size), counts)
    item_split = which[inverse]
    return tuple(np.flatnonzero(item_split == k).astype(np.int64) for k in range(counts.size))
