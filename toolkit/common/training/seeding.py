"""Seed control without global side effects.

Randomness in training comes from three places: the initial weights (torch's global
generator, which ``nn.Module`` constructors use), the batch order and the data split.
:func:`torch_seeded` builds a model under a given seed and restores torch's global
generator afterwards; :func:`generators` returns a numpy ``Generator`` and a CPU
``torch.Generator`` for the rest. Nothing is seeded at import.
"""

from __future__ import annotations

import contextlib

import numpy as np

__all__ = ["check_seed", "generators", "torch_seeded"]


def check_seed(seed) -> int:
    """``seed`` as a non-negative int, or a ValueError naming it."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def generators(seed: int):
    """``(numpy.random.Generator, torch.Generator)`` both seeded from ``seed`` (independent streams)."""
    import torch

    seed = check_seed(seed)
    ss = np.random.SeedSequence(seed)
    np_seed, torch_seed = ss.spawn(2)
    g = torch.Generator(device="cpu")
    g.manual_seed(int(torch_seed.generate_state(1, dtype=np.uint64)[0] >> np.uint64(1)))
    return np.random.default_rng(np_seed), g


@contextlib.contextmanager
def torch_seeded(seed: int):
    """Run the block with torch's global CPU generator seeded to ``seed``; its previous state
    is restored on exit (so building a model here changes nothing outside)."""
    import torch

    seed = check_seed(seed)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        yield
