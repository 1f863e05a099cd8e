"""The impact surrogates' networks: every one maps a batch of node time series of inputs
``(B, F, n_in)`` to outputs ``(B, F, n_out)`` (all scaled to [0, 1]).

- :class:`PerOutputLSTM`: the impact paper's model, one LSTM (``hidden`` units) with a 1-unit
  dense output per output channel, trained side by side (their parameters are disjoint,
  so this is ``n_out`` independent paper models);
- :class:`SequenceLSTM`: one (stacked) LSTM with a dense multi-output head;
- :class:`PointwiseMLP`: the non-recurrent baseline, the same per-frame inputs through a
  multilayer perceptron applied at every frame independently (no memory).

Any of them can take a :class:`PositionalEncoding` of the node position first (sines and
cosines of the scaled coordinates at octave frequencies, as in NeRF): the fields vary
sharply over the face near the contact, and networks of smooth units learn such
high-frequency functions of their inputs slowly without it (spectral bias).

Each frame's inputs (initial position, imposed velocity, time, fixed flag) determine the
whole history of earlier inputs, so recurrence adds no information, only a way to carry
state; the baseline measures what that buys.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["PerOutputLSTM", "SequenceLSTM", "PointwiseMLP", "PositionalEncoding", "Encoded", "build_network",
           "NETWORKS"]


class PerOutputLSTM(nn.Module):
    """``n_out`` models of the impact paper's kind: LSTM(``n_in`` -> ``hidden``) + Linear(``hidden`` -> 1) each."""

    def __init__(self, n_in: int, n_out: int, hidden: int = 5, layers: int = 1):
        super().__init__()
        self.lstms = nn.ModuleList(nn.LSTM(n_in, hidden, num_layers=layers, batch_first=True) for _ in range(n_out))
        self.heads = nn.ModuleList(nn.Linear(hidden, 1) for _ in range(n_out))

    def forward(self, x):
        return torch.cat([head(lstm(x)[0]) for lstm, head in zip(self.lstms, self.heads)], dim=-1)


class SequenceLSTM(nn.Module):
    """LSTM(``n_in`` -> ``hidden``, ``layers`` stacked) + Linear(``hidden`` -> ``n_out``)."""

    def __init__(self, n_in: int, n_out: int, hidden: int = 64, layers: int = 2):
        super().__init__()
        self.lstm = nn.LSTM(n_in, hidden, num_layers=layers, batch_first=True)
        self.head = nn.Linear(hidden, n_out)

    def forward(self, x):
        return self.head(self.lstm(x)[0])


class PointwiseMLP(nn.Module):
    """``layers`` hidden layers of ``hidden`` SiLU units applied to each frame's inputs alone."""

    def __init__(self, n_in: int, n_out: int, hidden: int = 128, layers: int = 3):
        super().__init__()
        dims = [n_in] + [hidden] * layers
        blocks = []
        for a, b in zip(dims[:-1], dims[1:]):
            blocks += [nn.Linear(a, b), nn.SiLU()]
        self.net = nn.Sequential(*blocks, nn.Linear(dims[-1], n_out))

    def forward(self, x):
        return self.net(x)


class PositionalEncoding(nn.Module):
    """Appends ``sin(2^k pi p), cos(2^k pi p)``, ``k = 0 .. octaves-1``, of the first 3 inputs
    ``p`` (the scaled position) to the inputs: ``(..., n_in) -> (..., n_in + 6 octaves)``."""

    def __init__(self, octaves: int):
        super().__init__()
        self.register_buffer("frequencies", (2.0 ** torch.arange(int(octaves), dtype=torch.float32)) * torch.pi)

    def forward(self, x):
        p = x[..., :3, None] * self.frequencies
        return torch.cat([x, torch.sin(p).flatten(-2), torch.cos(p).flatten(-2)], dim=-1)


class Encoded(nn.Module):
    """A network fed through a :class:`PositionalEncoding`."""

    def __init__(self, encoding: PositionalEncoding, net: nn.Module):
        super().__init__()
        self.encoding, self.net = encoding, net

    def forward(self, x):
        return self.net(self.encoding(x))


NETWORKS = {"per_output_lstm": PerOutputLSTM, "lstm": SequenceLSTM, "mlp": PointwiseMLP}


def build_network(kind: str, n_in: int, n_out: int, hidden: int, layers: int, fourier: int = 0) -> nn.Module:
    """The network ``kind`` (one of :data:`NETWORKS`) with the given sizes, behind a positional
    encoding of ``fourier`` octaves when ``fourier > 0``."""
    if kind not in NETWORKS:
        raise ValueError(f"network {kind!r} is not one of {sorted(NETWORKS)}")
    if int(hidden) < 1 or int(layers) < 1 or int(fourier) < 0:
        raise ValueError(f"hidden ({hidden}) and layers ({layers}) must be >= 1, fourier ({fourier}) >= 0")
    if not fourier:
        return NETWORKS[kind](n_in, n_out, int(hidden), int(layers))
    inner = NETWORKS[kind](n_in + 6 * int(fourier), n_out, int(hidden), int(layers))
    return Encoded(PositionalEncoding(fourier), inner)
