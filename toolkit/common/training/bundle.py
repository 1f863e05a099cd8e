"""A trained model on disk: ``model.pt`` (``torch.save`` of the state dict), ``weights.npz``
(the same state as numpy arrays, read without importing torch) and ``config.json`` (what it
is, how it was built, the data it was built for, its scalers).

:class:`ModelBundle` is model-agnostic: the workflow that owns a model (the impact
LSTM, the static PointNet++) rebuilds the network from ``config`` and loads the
weights. Loading refuses a directory of another kind or format version, and
:meth:`ModelBundle.check_data` refuses data whose signature (feature names, node count,
frames, scene...) differs from the one the model was trained on, naming each difference.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from toolkit.common.config_diff import IncompatibleError, jsonable, require_same
from toolkit.common.meshes.fingerprint import file_fingerprint
from toolkit.common.meshes.io import atomic_path
from toolkit.common.training.scaling import MinMaxScaler

__all__ = ["ModelBundle", "BUNDLE_FORMAT", "CALIBRATION_FILES", "IncompatibleError"]

BUNDLE_FORMAT = ("toolkit-model", 1)
#: the state dict as numpy arrays, keys of nested dicts joined by "/"
WEIGHT_ARRAYS = "weights.npz"

#: the files a calibration is saved to in a model directory
CALIBRATION_FILES = ("calibration.json", "calibration.npz")


@dataclass(frozen=True, eq=False)
class ModelBundle:
    """A model's weights with everything needed to use it again.

    Attributes
    ----------
    kind : what reads it (e.g. ``"toolkit.impact.surrogate"``)
    config : JSON-able architecture and training settings
    data : JSON-able signature of the training data (checked by :meth:`check_data`)
    scalers : name -> MinMaxScaler (inputs, outputs)
    state_dict : the network's ``state_dict()``
    extra : JSON-able facts (training time, history, split)
    """

    kind: str
    config: dict
    data: dict
    scalers: dict
    state_dict: dict
    extra: dict = field(default_factory=dict)

    def save(self, directory: str | os.PathLike) -> Path:
        """Write ``model.pt``, ``weights.npz`` then ``config.json`` (each atomically; the JSON
        last, so a directory with a ``config.json`` always has the weights it describes). A
        calibration in the directory, made for the weights these replace, is removed first."""
        import numpy as np
        import torch


        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        for name in CALIBRATION_FILES:  # made for the weights these replace
            (directory / name).unlink(missing_ok=True)
        flat = {key: torch.as_tensor(value).detach().cpu() for key, value in _flatten(self.state_dict).items()}
        with atomic_path(directory / "model.pt") as tmp:
            torch.save(_nest(flat), tmp)
        arrays = {key: value.numpy() for key, value in flat.items()}
        with atomic_path(directory / WEIGHT_ARRAYS) as tmp, open(tmp, "wb") as fh:
            np.savez(fh, **arrays)
        doc = {"format": BUNDLE_FORMAT[0], "format_version": BUNDLE_FORMAT[1], "kind": self.kind,
               "config": jsonable(self.config), "data": jsonable(self.data),
               "scalers": {k: s.to_dict() for k, s in self.scalers.items()}, "extra": jsonable(self.extra)}
        with atomic_path(directory / "config.json") as tmp:
            tmp.write_text(json.dumps(doc, indent=2))
        return directory

    @classmethod
    def load(cls, directory: str | os.PathLike, kind: str | None = None, map_location="cpu",
             arrays: bool = False) -> ModelBundle:
        """Read a model directory; ``kind`` (if given) must match the stored one. With
        ``arrays``, the state is read from ``weights.npz`` as numpy arrays (nested as the state
        dict) without importing torch; :meth:`has_arrays` says whether a directory has it."""
        directory = Path(directory)
        cfg, weights = directory / "config.json", directory / (WEIGHT_ARRAYS if arrays else "model.pt")
        for p in (cfg, weights):
            if not p.is_file():
                raise FileNotFoundError(f"{directory} is not a model directory: {p.name} is missing "
                                        f"(expected {weights.name} and config.json, as written by training)")
        try:
            doc = json.loads(cfg.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"{cfg} is not valid JSON: {exc}") from exc
        found = (doc.get("format"), doc.get("format_version"))
        if found != BUNDLE_FORMAT:
            raise ValueError(f"{cfg} has format {found}, expected {BUNDLE_FORMAT}")
        if kind is not None and doc.get("kind") != kind:
            raise IncompatibleError(f"{directory} holds a {doc.get('kind')!r} model, expected {kind!r}",
                                    [("kind", doc.get("kind"), kind)])
        try:
            state = _read_arrays(weights) if arrays else _read_torch(weights, map_location)
        except Exception as exc:
            raise ValueError(f"cannot read {weights}: {type(exc).__name__}: {exc}") from exc
        scalers = {k: MinMaxScaler.from_dict(v) for k, v in doc.get("scalers", {}).items()}
        return cls(doc["kind"], doc["config"], doc["data"], scalers, state, doc.get("extra", {}))

    @staticmethod
    def weights_sha1(directory: str | os.PathLike) -> str:
        """SHA-1 of a model directory's ``model.pt``: which weights a calibration was made for."""
        return file_fingerprint(Path(directory) / "model.pt")

    @staticmethod
    def has_arrays(directory: str | os.PathLike) -> bool:
        """Whether a model directory holds ``weights.npz`` (every one :meth:`save` writes)."""
        return (Path(directory) / WEIGHT_ARRAYS).is_file()

    def check_data(self, signature: dict, what: str = "the data", hint: str | None = None) -> None:
        """Refuse ``signature`` unless it equals the stored training-data signature; ``hint``
        replaces the default remedy of the message."""
        require_same(self.data, signature, f"this {self.kind} model",
                     hint=hint or f"{what} differs from what it was trained on; train a model on it")

    def check_config(self, config: dict, ignore: tuple[str, ...] = ()) -> None:
        """Refuse a configuration other than the stored one (e.g. loading the ``paper`` model's weights as ``strong``);
        keys in ``ignore`` (e.g. the training budget) may differ."""
        stored = {k: v for k, v in self.config.items() if k not in ignore}
        asked = {k: v for k, v in config.items() if k not in ignore}
        require_same(stored, asked, f"this {self.kind} model")


def _flatten(state: dict, prefix: str = "") -> dict:
    """``{"net": {"w": t}}`` -> ``{"net/w": t}`` (keys must not hold "/")."""
    flat = {}
    for key, value in state.items():
        if "/" in str(key):
            raise ValueError(f"state dict key {key!r} holds '/', which {WEIGHT_ARRAYS} uses to nest keys")
        if isinstance(value, dict):
            flat.update(_flatten(value, f"{prefix}{key}/"))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _read_arrays(path: Path) -> dict:
    """The nested state dict of a ``weights.npz`` (numpy arrays)."""
    import numpy as np

    with np.load(path, allow_pickle=False) as data:
        return _nest({key: data[key] for key in data.files})


def _nest(flat: dict) -> dict:
    """Inverse of :func:`_flatten`."""
    state: dict = {}
    for key, value in flat.items():
        *parents, leaf = key.split("/")
        node = state
        for parent in parents:
            node = node.setdefault(parent, {})
        node[leaf] = value
    return state


def _read_torch(path: Path, map_location) -> dict:
    import torch

    return torch.load(path, map_location=map_location, weights_only=True)
