"""A trained model on disk: ``model.pt`` (``torch.save`` of the state dict) and
``config.json`` (what it is, how it was built, the data it was built for, its scalers).

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
from toolkit.common.training.scaling import MinMaxScaler

__all__ = ["ModelBundle", "BUNDLE_FORMAT", "IncompatibleError"]

BUNDLE_FORMAT = ("toolkit-model", 1)


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
        """Write ``model.pt`` then ``config.json`` (each atomically; the JSON last, so a directory
        with a ``config.json`` always has the weights it describes)."""
        import torch

        from toolkit.common.io import atomic_path

        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        with atomic_path(directory / "model.pt") as tmp:
            torch.save(self.state_dict, tmp)
        doc = {"format": BUNDLE_FORMAT[0], "format_version": BUNDLE_FORMAT[1], "kind": self.kind,
               "config": jsonable(self.config), "data": jsonable(self.data),
               "scalers": {k: s.to_dict() for k, s in self.scalers.items()}, "extra": jsonable(self.extra)}
        with atomic_path(directory / "config.json") as tmp:
            tmp.write_text(json.dumps(doc, indent=2))
        return directory

    @classmethod
    def load(cls, directory: str | os.PathLike, kind: str | None = None, map_location="cpu") -> ModelBundle:
        """Read a model directory; ``kind`` (if given) must match the stored one."""
        import torch

        directory = Path(directory)
        cfg, weights = directory / "config.json", directory / "model.pt"
        for p in (cfg, weights):
            if not p.is_file():
                raise FileNotFoundError(f"{directory} is not a model directory: {p.name} is missing "
                                        "(expected model.pt and config.json, as written by training)")
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
            state = torch.load(weights, map_location=map_location, weights_only=True)
        except Exception as exc:
            raise ValueError(f"cannot read {weights}: {type(exc).__name__}: {exc}") from exc
        scalers = {k: MinMaxScaler.from_dict(v) for k, v in doc.get("scalers", {}).items()}
        return cls(doc["kind"], doc["config"], doc["data"], scalers, state, doc.get("extra", {}))

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
