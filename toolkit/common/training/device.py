"""Where a model runs: ``"cpu"`` (the default), ``"cuda"`` / ``"cuda:N"``, or ``"auto"``
(CUDA when torch sees a GPU, else CPU)."""

from __future__ import annotations

__all__ = ["resolve_device"]


def resolve_device(device: str = "cpu"):
    """The ``torch.device`` for ``device``; a clear ValueError for a CUDA device torch cannot see."""
    import torch

    if not isinstance(device, str):
        raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {device!r}")
    name = device.strip().lower()
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cpu":
        return torch.device("cpu")
    if name == "cuda" or name.startswith("cuda:"):
        if not torch.cuda.is_available():
            raise ValueError(f"device {device!r} asked for, but this torch ({torch.__version__}) sees no CUDA GPU; "
                             "use 'cpu' or 'auto'")
        dev = torch.device(name)
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"device {device!r}: only {torch.cuda.device_count()} CUDA device(s) visible")
        return dev
    raise ValueError(f"device must be 'cpu', 'cuda', 'cuda:N' or 'auto', got {device!r}")
