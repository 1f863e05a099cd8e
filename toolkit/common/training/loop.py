"""One training loop for every surrogate: Adam, a loss of the caller's choice, early stopping
on a validation set, atomic checkpoints and resume.

:func:`train` works on in-memory tensors (the surrogates' data fit in memory here): each
epoch shuffles the training items with a seeded ``torch.Generator``, steps Adam on
mini-batches, then scores the validation set. The weights with the lowest validation
loss are kept and restored at the end. With ``checkpoint=path`` the full state (model,
optimizer, best weights, epoch, history, generator state, configuration) is written
atomically after every epoch, so an interrupted run (Ctrl-C, a killed job) resumes
from the last finished epoch with ``resume=True`` and continues exactly as if it had
not stopped. A checkpoint made for another configuration is refused, naming the
difference.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common.config_diff import jsonable, require_same
from toolkit.common.meshes.io import atomic_path
from toolkit.common.training.device import resolve_device
from toolkit.common.training.seeding import check_seed, generators

if TYPE_CHECKING:  # pragma: no cover
    import pandas as pd

__all__ = ["TrainConfig", "TrainResult", "train", "learning_rate", "stop_reason", "CHECKPOINT_FORMAT", "LR_SCHEDULES"]

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = ("toolkit-checkpoint", 1)
LR_SCHEDULES = ("constant", "cosine")


@dataclass(frozen=True)
class TrainConfig:
    """Optimisation settings.

    Attributes
    ----------
    epochs : maximum passes over the training set
    batch_size : items per Adam step (the impact paper: 10,000)
    lr : Adam learning rate; weight_decay : Adam's L2 factor
    patience : stop after this many epochs without a validation improvement (None: never)
    min_delta : relative improvement of the validation loss that counts (0.01 = 1 %)
    seed : shuffling seed (weights are seeded by the caller, see ``torch_seeded``)
    device : ``cpu`` / ``cuda`` / ``auto``
    max_seconds : stop after this much training time (None: no limit)
    grad_clip : clip the gradient norm to this (None: no clipping)
    lr_schedule : ``constant`` (Adam at ``lr`` throughout) or ``cosine``: before each epoch the
        rate is ``lr * (f + (1 - f) * (1 + cos(pi p)) / 2)`` with ``f = final_lr_fraction`` and
        ``p`` the budget spent so far, the larger of ``epoch / epochs`` and (with a time limit)
        ``seconds / max_seconds``; so a time-limited run ends at the small rate whatever the
        machine's speed, and a resumed run continues the same curve
    final_lr_fraction : rate at the end of a ``cosine`` schedule, as a fraction of ``lr``
    progress : tqdm bar over epochs
    """

    epochs: int = 100
    batch_size: int = 10_000
    lr: float = 1e-3
    weight_decay: float = 0.0
    patience: int | None = 20
    min_delta: float = 0.0
    seed: int = 0
    device: str = "cpu"
    max_seconds: float | None = None
    grad_clip: float | None = None
    lr_schedule: str = "constant"
    final_lr_fraction: float = 0.01
    progress: bool = True

    #: settings that may differ when resuming (they do not change what was learned so far)
    RESUMABLE = ("epochs", "device", "max_seconds", "progress", "patience")

    def __post_init__(self):
        if int(self.epochs) < 1 or int(self.batch_size) < 1:
            raise ValueError(f"epochs ({self.epochs}) and batch_size ({self.batch_size}) must be >= 1")
        if not self.lr > 0 or self.weight_decay < 0 or self.min_delta < 0:
            raise ValueError(f"lr ({self.lr}) must be > 0, weight_decay ({self.weight_decay}) and min_delta "
                             f"({self.min_delta}) >= 0")
        if self.lr_schedule not in LR_SCHEDULES:
            raise ValueError(f"lr_schedule {self.lr_schedule!r} is not one of {LR_SCHEDULES}")
        if not 0.0 < self.final_lr_fraction <= 1.0:
            raise ValueError(f"final_lr_fraction = {self.final_lr_fraction!r}; expected a number in (0, 1]")
        if self.patience is not None and int(self.patience) < 1:
            raise ValueError(f"patience must be >= 1 or None, got {self.patience}")
        check_seed(self.seed)


@dataclass(frozen=True, eq=False)
class TrainResult:
    """What :func:`train` did.

    Attributes
    ----------
    history : DataFrame, one row per epoch: ``epoch``, ``train_loss``, ``val_loss``, ``seconds``
        (cumulative training time, s), ``lr`` (Adam's rate during the epoch)
    best_epoch : epoch (1-based) whose weights the model now holds
    best_val_loss : its validation loss
    seconds : training time, s, summed over resumed sessions
    stopped : ``"epochs"``, ``"early_stopping"`` or ``"time_limit"`` (in words: :attr:`stop_reason`)
    resumed_from : the epoch a resumed run started after, or None
    """

    history: pd.DataFrame
    best_epoch: int
    best_val_loss: float
    seconds: float
    stopped: str
    resumed_from: int | None = None
    extra: dict = field(default_factory=dict)
    config: TrainConfig | None = None

    @property
    def stop_reason(self) -> str:
        """Why training stopped, in words (e.g. ``"epoch limit of 200 reached"``)."""
        return stop_reason(self.stopped, self.config)


def stop_reason(stopped: str, config: TrainConfig | None = None) -> str:
    """``stopped`` (``"epochs"``, ``"early_stopping"``, ``"time_limit"``) in words, with the limit
    from ``config`` when given."""
    c = config
    words = {
        "epochs": f"epoch limit of {c.epochs} reached" if c else "epoch limit reached",
        "early_stopping": (f"early stopping: no validation improvement in {c.patience} epochs" if c
                           else "early stopping: no validation improvement"),
        "time_limit": f"time limit of {c.max_seconds:.0f} s reached" if c and c.max_seconds else "time limit reached",
    }
    if stopped not in words:
        raise ValueError(f"stopped = {stopped!r}; expected one of {list(words)}")
    return words[stopped]


def learning_rate(config: TrainConfig, epochs_done: int, seconds: float) -> float:
    """Adam's rate for the next epoch after ``epochs_done`` epochs and ``seconds`` of training."""
    if config.lr_schedule == "constant":
        return config.lr
    spent = epochs_done / config.epochs
    if config.max_seconds is not None and config.max_seconds > 0:
        spent = max(spent, seconds / config.max_seconds)
    f = config.final_lr_fraction
    return config.lr * (f + (1.0 - f) * 0.5 * (1.0 + np.cos(np.pi * min(spent, 1.0))))


def _tensors(data, device):
    import torch

    def one(a):
        t = torch.as_tensor(np.asarray(a) if not isinstance(a, torch.Tensor) else a)
        if t.is_floating_point():
            t = t.to(torch.float32)
        return t.to(device)

    inputs, targets = data
    inputs = tuple(one(a) for a in (inputs if isinstance(inputs, (tuple, list)) else (inputs,)))
    targets = one(targets)
    n = targets.shape[0]
    for i, a in enumerate(inputs):
        if a.shape[0] != n:
            raise ValueError(f"input {i} has {a.shape[0]} items, the targets {n}; they must match on axis 0")
    if n == 0:
        raise ValueError("no items to train or validate on")
    return inputs, targets


def _state_copy(model):
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def train(model, loss: Callable, train_data, val_data, config: TrainConfig = TrainConfig(),
          checkpoint: str | Path | None = None, resume: bool = False, identity: dict | None = None) -> TrainResult:
    """Train ``model`` in place and leave it holding the best validation weights.

    Parameters
    ----------
    model : torch.nn.Module, called as ``model(*inputs)``
    loss : ``loss(prediction, target) -> scalar tensor`` (e.g. ``torch.nn.functional.l1_loss``, MAE)
    train_data, val_data : ``(inputs, targets)``; ``inputs`` an array/tensor or a tuple of them,
        all sharing the item axis 0 with ``targets``; float arrays become float32
    config : TrainConfig
    checkpoint : file to write the full training state to after every epoch (atomically)
    resume : continue from ``checkpoint`` if it exists (its configuration must match)
    identity : JSON-able description of the model and data (architecture, scalers, data
        signature) that a checkpoint must share to be resumed

    Returns
    -------
    TrainResult
    """
    import pandas as pd
    import torch
    from tqdm.auto import tqdm

    device = resolve_device(config.device)
    model.to(device)
    x_tr, y_tr = _tensors(train_data, device)
    x_va, y_va = _tensors(val_data, device)
    opt = torch.optim.Adam(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    _, gen = generators(config.seed)
    described = jsonable({"identity": identity or {},
                          "train": {k: v for k, v in asdict(config).items() if k not in TrainConfig.RESUMABLE}})
    history, best_state, best_val, best_epoch, bad, start, elapsed = [], None, np.inf, 0, 0, 0, 0.0
    resumed_from = None
    checkpoint = Path(checkpoint) if checkpoint is not None else None
    if resume and checkpoint is not None and checkpoint.exists():
        state = _load_checkpoint(checkpoint, device)
        require_same(state["described"], described, f"checkpoint {checkpoint}",
                     hint="resume with the settings it was started with, or start afresh without resume")
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        gen.set_state(state["generator"])
        history, best_state, best_val = state["history"], state["best_model"], state["best_val"]
        best_epoch, bad, start, elapsed = state["best_epoch"], state["bad_epochs"], state["epoch"], state["seconds"]
        resumed_from = start
        log.info("resumed %s after epoch %d (best %.4g at epoch %d)", checkpoint, start, best_val, best_epoch)
    n, bs = y_tr.shape[0], int(config.batch_size)
    stopped = "epochs"
    if config.patience is not None and bad >= config.patience:
        stopped = "early_stopping"
    bar = tqdm(total=config.epochs, initial=min(start, config.epochs), desc="epochs", disable=not config.progress,
               leave=False)
    try:
        for epoch in range(start + 1, config.epochs + 1):
            if stopped != "epochs":
                break
            t0 = time.perf_counter()
            rate = learning_rate(config, epoch - 1, elapsed)
            for group in opt.param_groups:
                group["lr"] = rate
            model.train()
            perm = torch.randperm(n, generator=gen).to(device)
            total = 0.0
            for i in range(0, n, bs):
                idx = perm[i:i + bs]
                opt.zero_grad(set_to_none=True)
                value = loss(model(*(x[idx] for x in x_tr)), y_tr[idx])
                if not torch.isfinite(value):
                    raise FloatingPointError(f"training loss became {value.item()} at epoch {epoch}; lower the "
                                             f"learning rate ({config.lr}) or check the data scaling")
                value.backward()
                if config.grad_clip is not None:
                    torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
                opt.step()
                total += float(value.detach()) * idx.numel()
            val = evaluate_loss(model, loss, x_va, y_va, bs)
            elapsed += time.perf_counter() - t0
            history.append({"epoch": epoch, "train_loss": total / n, "val_loss": val, "seconds": elapsed, "lr": rate})
            if val < best_val * (1.0 - config.min_delta) or best_state is None:
                best_val, best_epoch, best_state, bad = val, epoch, _state_copy(model), 0
            else:
                bad += 1
            if config.patience is not None and bad >= config.patience:
                stopped = "early_stopping"
            elif config.max_seconds is not None and elapsed >= config.max_seconds:
                stopped = "time_limit"
            if checkpoint is not None:
                _save_checkpoint(checkpoint, {
                    "format": CHECKPOINT_FORMAT[0], "format_version": CHECKPOINT_FORMAT[1], "described": described,
                    "epoch": epoch, "model": model.state_dict(), "optimizer": opt.state_dict(),
                    "best_model": best_state, "best_val": best_val, "best_epoch": best_epoch, "bad_epochs": bad,
                    "history": history, "generator": gen.get_state(), "seconds": elapsed})
            bar.set_postfix(train=f"{total / n:.3g}", val=f"{val:.3g}", best=best_epoch)
            bar.update(1)
    finally:  # Ctrl-C lands here too: the last checkpoint on disk is a finished epoch's
        bar.close()
    if best_state is not None:
        model.load_state_dict(best_state)
    return TrainResult(pd.DataFrame(history, columns=["epoch", "train_loss", "val_loss", "seconds", "lr"]),
                       int(best_epoch), float(best_val), float(elapsed), stopped, resumed_from, config=config)


def evaluate_loss(model, loss: Callable, inputs, targets, batch_size: int) -> float:
    """Mean of ``loss`` over the items (batch losses weighted by batch size), no gradients."""
    import torch

    model.eval()
    total, n = 0.0, targets.shape[0]
    with torch.no_grad():
        for i in range(0, n, batch_size):
            sl = slice(i, i + batch_size)
            total += float(loss(model(*(x[sl] for x in inputs)), targets[sl])) * targets[sl].shape[0]
    return total / n


def _save_checkpoint(path: Path, state: dict) -> None:
    import torch


    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def _load_checkpoint(path: Path, device) -> dict:
    import torch

    try:
        state = torch.load(path, map_location=device, weights_only=False)
    except Exception as exc:  # a truncated or foreign file
        raise ValueError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}") from exc
    if not isinstance(state, dict) or (state.get("format"), state.get("format_version")) != CHECKPOINT_FORMAT:
        found = (state.get("format"), state.get("format_version")) if isinstance(state, dict) else type(state).__name__
        raise ValueError(f"{path} is not a toolkit training checkpoint (found {found}, expected {CHECKPOINT_FORMAT})")
    return state
