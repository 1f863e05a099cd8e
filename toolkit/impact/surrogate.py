"""The LSTM surrogate of the impact simulation (the impact paper) and its baselines.

An *item* is one node's time series at one imposed velocity. Its inputs at frame ``k``
(:data:`FEATURES`) are, for the impact paper's set (``paper``), the node's initial position
``x0, y0, z0`` (mm), the ball's velocity (mm/s), the time ``t_k`` (s) and whether the scene
holds the node (0/1); the ``ball`` set adds what the scene defines about the ball at that
time: its travel ``v t_k`` (mm) and the node's signed distance to the ball's nominal
sphere ``|x0 - c(t_k)| - R`` (mm, negative once the undeformed node would be inside it).
Outputs are the displacement ``ux, uy, uz`` (mm) and the von Mises stress (MPa). Inputs
and outputs are min-max scaled to [0, 1] with scalers fitted on the training items and
saved with the model.

Configurations (:data:`CONFIGS`):

- ``paper``: the impact paper's model, LSTM with 5 hidden units and 1 output, one per output
  channel (so 4 models: ux, uy, uz, von Mises), MAE loss, Adam, batches of 10,000 items,
  the impact paper's inputs;
- ``strong`` (the default of :func:`train_surrogate`): one multi-output LSTM with the ``ball``
  inputs and an MSE loss, chosen by measurement (``benchmarks/impact_surrogate.py --sweep``;
  README), its learning rate decayed on a cosine over the training budget (paper database,
  random split: a lower displacement RMSE than at a constant rate, in a similar training time);
- ``baseline``: a multilayer perceptron applied to each frame independently (no
  recurrence), with the same inputs and loss as ``strong``.

Splits (:func:`split_items`): ``random``, the impact paper's item split (76 % of the training
velocities' items for training, the rest for testing); ``velocity``, every item of the
training velocities for training and the held-out velocities' simulations, never seen, for
testing. Validation (early stopping) takes 10 % of the training items.

After prediction, nodes the scene holds are given zero displacement (the boundary
condition, enforced in the output rather than learned), and the von Mises stress is clamped
at zero once unscaled: the network regresses a scaled stress that can come out below zero,
and a von Mises stress is a norm, so ``max(s, 0)`` is never farther than ``s`` from the true
stress (every error stays the same or shrinks, with no retraining).
"""

from __future__ import annotations

import logging
import os
import time
import warnings
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common.config_diff import require_same
from toolkit.common.meshes.fingerprint import points_fingerprint
from toolkit.common.meshes.io import TimeSeriesWriter
from toolkit.common.outputs import check_output_dir
from toolkit.common.training import (
    MinMaxScaler,
    ModelBundle,
    TrainConfig,
    extrapolation,
    resolve_device,
    split_groups,
    torch_seeded,
    train,
)
from toolkit.impact.checks import answer_checks
from toolkit.impact.database import ImpactDatabase, SceneInputs, load_database
from toolkit.impact.scene import Scene
from toolkit.impact.simulate import ball_start, face_mesh, write_preview, write_summary

if TYPE_CHECKING:  # pragma: no cover
    from types import FrameType

    from toolkit.common.meshes.mesh import Mesh
    from toolkit.impact.scene import Scene

__all__ = ["SurrogateConfig", "CONFIGS", "FEATURES", "INPUTS", "OUTPUTS", "MODEL_KIND", "SPLITS", "item_features",
           "item_targets", "split_items", "train_surrogate", "Surrogate", "ExtrapolationWarning", "Prediction",
           "predict_scene"]

log = logging.getLogger(__name__)

MODEL_KIND = "toolkit.impact.surrogate"
#: the input feature sets (names with units)
FEATURES = {
    "paper": ("x0_mm", "y0_mm", "z0_mm", "velocity_mm_s", "time_s", "fixed"),
    "ball": ("x0_mm", "y0_mm", "z0_mm", "velocity_mm_s", "time_s", "fixed", "travel_mm", "ball_gap_mm"),
}
INPUTS = FEATURES["paper"]
OUTPUTS = ("ux_mm", "uy_mm", "uz_mm", "von_mises_mpa")
SPLITS = ("random", "velocity")
#: the impact paper: 450,000 of 592,260 items for training
RANDOM_TRAIN_FRACTION = 0.76
VALIDATION_FRACTION = 0.1
#: the networks of :mod:`toolkit.impact.networks` (named here so that importing this module does not import torch)
NETWORK_NAMES = ("per_output_lstm", "lstm", "mlp")


class ExtrapolationWarning(UserWarning):
    """A prediction asked for a velocity outside the range the model was trained on."""


@dataclass(frozen=True)
class SurrogateConfig:
    """Network and optimisation settings of one surrogate configuration.

    Attributes
    ----------
    name : label (``paper``, ``strong``, ``baseline`` or your own)
    network : ``per_output_lstm``, ``lstm`` or ``mlp`` (:mod:`toolkit.impact.networks`)
    hidden, layers : units per layer, stacked layers
    features : input set, a key of :data:`FEATURES`
    fourier : octaves of the positional encoding of the node position (0: none)
    per_travel : learn the outputs divided by the ball's travel ``v t`` (mm) and multiply back:
        the fields start from zero with the travel by construction, and in this quasi-static
        scene (the ball moves at ~1 % of the shear-wave speed) they grow roughly with it
    loss : ``mae`` (the impact paper) or ``mse``
    lr : Adam learning rate; batch_size : items (node series) per step
    lr_schedule : ``constant`` (the impact paper) or ``cosine`` (decays to 1 % of ``lr`` over the
        training budget, see :class:`~toolkit.common.training.TrainConfig`)
    epochs, patience : at most this many epochs; stop after ``patience`` without improvement
    max_seconds : training time limit, s
    """

    name: str
    network: str
    hidden: int
    layers: int = 1
    features: str = "paper"
    fourier: int = 0
    per_travel: bool = False
    loss: str = "mae"
    lr: float = 1e-3
    batch_size: int = 10_000
    lr_schedule: str = "constant"
    epochs: int = 300
    patience: int | None = 30
    max_seconds: float = 900.0

    def __post_init__(self):
        for key in ("name", "features"):  # "seed": the spelling in models saved by toolkit 0.1
            if getattr(self, key) == "seed":
                object.__setattr__(self, key, "paper")
        if self.network not in NETWORK_NAMES:
            raise ValueError(f"network {self.network!r} is not one of {list(NETWORK_NAMES)}")
        if self.loss not in ("mae", "mse"):
            raise ValueError(f"loss {self.loss!r} must be 'mae' or 'mse'")
        if self.features not in FEATURES:
            raise ValueError(f"features {self.features!r} is not one of {sorted(FEATURES)}")

    #: settings that set how long training may run, not what the model is
    BUDGET = ("epochs", "patience", "max_seconds")

    def identity(self) -> dict:
        """The settings that define the model (everything but the training budget)."""
        return {k: v for k, v in asdict(self).items() if k not in self.BUDGET}

    @property
    def inputs(self) -> tuple[str, ...]:
        return FEATURES[self.features]

    def with_(self, **kw) -> SurrogateConfig:
        return replace(self, **kw)

    def train_config(self, seed: int, device: str, progress: bool) -> TrainConfig:
        return TrainConfig(epochs=self.epochs, batch_size=self.batch_size, lr=self.lr, patience=self.patience,
                           seed=seed, device=device, max_seconds=self.max_seconds, progress=progress,
                           lr_schedule=self.lr_schedule)


#: the three configurations of the benchmark (``strong``'s sizes: see README, chosen by measurement)
CONFIGS = {
    "paper": SurrogateConfig("paper", "per_output_lstm", hidden=5, layers=1, features="paper", loss="mae", lr=1e-3,
                            batch_size=10_000),
    "strong": SurrogateConfig("strong", "lstm", hidden=32, layers=1, features="ball", fourier=6, per_travel=True,
                              loss="mse", lr=3e-3, batch_size=256, lr_schedule="cosine"),
    "baseline": SurrogateConfig("baseline", "mlp", hidden=128, layers=3, features="ball", fourier=6, per_travel=True,
                                loss="mse", lr=3e-3, batch_size=256),
}


def resolve_config(config: SurrogateConfig | str) -> SurrogateConfig:
    """A :data:`CONFIGS` name or a SurrogateConfig."""
    cfg = CONFIGS.get(config, config) if isinstance(config, str) else config
    if not isinstance(cfg, SurrogateConfig):
        raise ValueError(f"config {config!r} is not one of {sorted(CONFIGS)} or a SurrogateConfig")
    return cfg


def item_features(inputs, velocities, features: str = "paper") -> np.ndarray:
    """Inputs of every item, ``(S * N, F, k)`` float32 in ``FEATURES[features]`` order (sim-major).

    inputs : :class:`~toolkit.impact.database.SceneInputs` (points (N, 3) mm, fixed (N,), times (F,) s,
        the ball's path); velocities : (S,) mm/s
    """
    names = FEATURES[features]
    v = np.asarray(velocities, dtype=np.float64).reshape(-1)
    points, times = inputs.points, inputs.times
    n, f, s = points.shape[0], times.shape[0], v.size
    x = np.empty((s, n, f, len(names)), dtype=np.float32)
    x[..., 0:3] = points[None, :, None, :]
    x[..., 3] = v[:, None, None]
    x[..., 4] = times[None, None, :]
    x[..., 5] = np.asarray(inputs.fixed, dtype=np.float32)[None, :, None]
    if features == "ball":
        travel = v[:, None] * times[None, :]  # (S, F) mm
        x[..., 6] = travel[:, None, :]
        centre = inputs.ball_centre0 + travel[..., None] * inputs.ball_direction  # (S, F, 3)
        for k in range(s):  # one simulation at a time keeps the (N, F, 3) temporary small
            x[k, ..., 7] = np.linalg.norm(points[:, None, :] - centre[k][None], axis=-1) - inputs.ball_radius
    return x.reshape(s * n, f, len(names))


def item_targets(db: ImpactDatabase, sims: np.ndarray | None = None) -> np.ndarray:
    """Outputs of every item of the simulations ``sims`` (default all), ``(S * N, F, 4)`` float32."""
    sims = np.arange(db.velocities.size) if sims is None else np.asarray(sims)
    u = np.moveaxis(db.displacement[sims], 1, 2)  # (S, N, F, 3)
    vm = np.moveaxis(db.von_mises[sims], 1, 2)[..., None]
    return np.concatenate([u, vm], axis=-1).reshape(-1, db.times.size, len(OUTPUTS)).astype(np.float32)


def split_items(db: ImpactDatabase, split: str, seed: int) -> dict[str, np.ndarray]:
    """Item indices (into :func:`item_features` of all simulations) for ``train``, ``val``, ``test``.

    ``random``: the items of the training velocities, 76 % train+val / 24 % test (whole node
    series; the impact paper's proportion). ``velocity``: all items of the training velocities for
    train+val, every item of the held-out velocities for test. Validation is 10 % of train+val.
    """
    if split not in SPLITS:
        raise ValueError(f"split {split!r} is not one of {SPLITS}")
    n = db.n_nodes
    sim_of_item = np.repeat(np.arange(db.velocities.size), n)
    training = np.flatnonzero(~db.held_out[sim_of_item])
    if split == "random":
        a, b = split_groups(training, (RANDOM_TRAIN_FRACTION, 1.0 - RANDOM_TRAIN_FRACTION), seed)
        pool, test = training[a], training[b]
    else:
        if not db.held_out.any():
            raise ValueError(f"{db.path} has no held-out velocity; build it with held-out velocities "
                             "(toolkit impact database --held-out ...) or use the random split")
        pool, test = training, np.flatnonzero(db.held_out[sim_of_item])
    tr, va = split_groups(pool, (1.0 - VALIDATION_FRACTION, VALIDATION_FRACTION), seed + 1)
    return {"train": pool[tr], "val": pool[va], "test": test}


def _travel(x: np.ndarray) -> np.ndarray:
    """The ball's travel ``v t`` (mm) of item inputs ``(B, F, k)`` as ``(B, F, 1)`` (every set has v, t)."""
    return (x[..., 3] * x[..., 4])[..., None]


def _loss(name: str):
    import torch

    return torch.nn.functional.l1_loss if name == "mae" else torch.nn.functional.mse_loss


def train_surrogate(db: ImpactDatabase | str | os.PathLike, config: SurrogateConfig | str = "strong",
                    split: str = "random", *, out: str | os.PathLike | None = None, seed: int = 0,
                    device: str = "cpu", resume: bool = False, progress: bool = True) -> Surrogate:
    """Train a surrogate on an impact database.

    Parameters
    ----------
    db : ImpactDatabase or the path of one
    config : a :data:`CONFIGS` name or a SurrogateConfig (default ``strong``, the best measured;
        ``paper`` for the impact paper's per-output LSTM)
    split : ``random`` or ``velocity`` (see :func:`split_items`)
    out : model directory; ``model.pt`` + ``config.json`` are written at the end and
        ``checkpoint.pt`` after every epoch (``resume=True`` continues from it)
    seed : weights, batch order and split
    device : ``cpu`` (default), ``cuda`` or ``auto``

    Returns
    -------
    Surrogate (its ``bundle.extra`` holds ``train_seconds``, ``history``, ``split``)
    """
    import torch

    from toolkit.impact.networks import build_network

    if out is not None:
        check_output_dir(out, what="model directory")
    resolve_device(device)  # a device torch does not see is refused before the model directory is made
    db = load_database(db) if not isinstance(db, ImpactDatabase) else db
    cfg = resolve_config(config)
    idx = split_items(db, split, seed)
    x_all = item_features(db.inputs, db.velocities, cfg.features)
    y_all = item_targets(db)
    if cfg.per_travel:
        y_all /= _travel(x_all)
    x_scaler = MinMaxScaler.fit(x_all[idx["train"]], cfg.inputs)
    y_scaler = MinMaxScaler.fit(y_all[idx["train"]], OUTPUTS)

    train_data, val_data = ((x_scaler.transform(x_all[idx[which]]).astype(np.float32),
                             y_scaler.transform(y_all[idx[which]]).astype(np.float32)) for which in ("train", "val"))
    del x_all, y_all
    with torch_seeded(seed):
        net = build_network(cfg.network, len(cfg.inputs), len(OUTPUTS), cfg.hidden, cfg.layers, cfg.fourier)
    split_spec = {"kind": split, "seed": seed, "train_fraction": RANDOM_TRAIN_FRACTION if split == "random" else None,
                  "validation_fraction": VALIDATION_FRACTION,
                  "train_velocities": db.velocities[~db.held_out].tolist(),
                  "held_out_velocities": db.velocities[db.held_out].tolist()}
    identity = {"config": cfg.identity(), "data": db.signature(), "split": split_spec,
                "scalers": {"inputs": x_scaler.to_dict(), "outputs": y_scaler.to_dict()}}
    checkpoint = None
    if out is not None:
        Path(out).mkdir(parents=True, exist_ok=True)
        checkpoint = Path(out) / "checkpoint.pt"
    result = train(net, _loss(cfg.loss), train_data, val_data, cfg.train_config(seed, device, progress),
                   checkpoint=checkpoint, resume=resume, identity=identity)
    net.to("cpu")
    extra = {"train_seconds": result.seconds, "best_epoch": result.best_epoch, "epochs_run": len(result.history),
             "best_val_loss": result.best_val_loss, "stopped": result.stopped, "stop_reason": result.stop_reason,
             "split": split_spec,
             "n_train_items": int(idx["train"].size), "n_val_items": int(idx["val"].size),
             "history": result.history.to_dict(orient="list"), "torch_threads": torch.get_num_threads(),
             "device": device}
    bundle = ModelBundle(MODEL_KIND, asdict(cfg), db.signature(),
                         {"inputs": x_scaler, "outputs": y_scaler},
                         {k: v.detach().clone() for k, v in net.state_dict().items()}, extra)
    surrogate = Surrogate(bundle, net, out)
    if out is not None:
        bundle.save(out)
    return surrogate


class Surrogate:
    """A trained impact surrogate: predicts displacement and von Mises time series of every node.

    Build with :func:`train_surrogate` or :meth:`load`; ``bundle`` holds config, scalers and the
    data signature, ``network`` the torch module (CPU), ``directory`` the model directory it was
    saved to or loaded from (None for a model never saved).
    """

    def __init__(self, bundle: ModelBundle, network, directory: str | os.PathLike | None = None):
        self.bundle, self.network = bundle, network
        self.directory = None if directory is None else Path(directory)
        self.config = SurrogateConfig(**bundle.config)
        self.network.eval()

    @classmethod
    def load(cls, directory: str | os.PathLike, config: str | SurrogateConfig | None = None) -> Surrogate:
        """Read a model directory. ``config`` (a name or SurrogateConfig), if given, must be the
        one the model was trained with; a mismatch is refused naming the differing settings."""
        from toolkit.impact.networks import build_network

        bundle = ModelBundle.load(directory, kind=MODEL_KIND)
        if config is not None:
            expected = resolve_config(config)
            # through the dataclass, so a setting missing from a saved model reads as its default
            require_same(SurrogateConfig(**bundle.config).identity(), expected.identity(), f"this {MODEL_KIND} model")
        cfg = SurrogateConfig(**bundle.config)
        net = build_network(cfg.network, len(cfg.inputs), len(OUTPUTS), cfg.hidden, cfg.layers, cfg.fourier)
        try:
            net.load_state_dict(bundle.state_dict)
        except RuntimeError as exc:
            raise ValueError(f"{directory}/model.pt does not fit the network its config.json describes "
                             f"({cfg.network}, hidden {cfg.hidden}, layers {cfg.layers}): {exc}") from exc
        return cls(bundle, net, directory)

    # ------------------------------------------------------------------ data checks
    def check_database(self, db: ImpactDatabase) -> None:
        """Refuse a database of another face, scene or frame times than the training one."""
        self.bundle.check_data(db.signature(), what=f"database {db.path}")

    @property
    def velocity_range(self) -> tuple[float, float]:
        v = self.bundle.extra["split"]["train_velocities"]
        return float(min(v)), float(max(v))

    def extrapolation(self, velocity: float) -> dict:
        """Whether ``velocity`` mm/s lies outside the training velocities: ``{"outside": bool,
        "parameters": {"velocity_mm_s": {"value", "train_range", "outside_by"}}}`` (listed only
        when outside, ``outside_by`` in mm/s; :func:`toolkit.common.training.extrapolation`);
        ``"outside": "unknown"`` for a model that does not record its training velocities."""
        v = self.bundle.extra.get("split", {}).get("train_velocities")
        return extrapolation({"velocity_mm_s": float(velocity)},
                             {"velocity_mm_s": [min(v), max(v)]} if v else None, "velocities")

    # ------------------------------------------------------------------ prediction
    def predict_items(self, x: np.ndarray, batch_size: int = 20_000):
        """Outputs ``(B, F, 4)`` (mm, MPa) of item inputs ``x (B, F, k)`` in the model's input order
        (:func:`item_features`); items whose ``fixed`` input is 1 get zero displacement, and the
        von Mises stress (channel 3) is ``max(decoded, 0)``, never negative."""
        import torch

        xs = self.bundle.scalers["inputs"].transform(np.asarray(x, dtype=np.float64)).astype(np.float32)
        out = np.empty(xs.shape[:2] + (len(OUTPUTS),), dtype=np.float64)
        with torch.no_grad():
            for i in range(0, xs.shape[0], batch_size):
                y = self.network(torch.from_numpy(xs[i:i + batch_size])).numpy()
                out[i:i + batch_size] = self.bundle.scalers["outputs"].inverse(y.astype(np.float64))
        if self.config.per_travel:
            out *= _travel(x)
        held = np.asarray(x[:, 0, 5] > 0.5)
        out[held, :, :3] = 0.0
        out[..., 3] = np.maximum(out[..., 3], 0.0)
        return out

    def predict(self, velocity: float, inputs):
        """Whole-face prediction at ``velocity`` mm/s for the scene's ``inputs``
        (:class:`~toolkit.impact.database.SceneInputs`): ``(displacement (F, N, 3) mm,
        von_mises (F, N) MPa, >= 0)``; warns :class:`ExtrapolationWarning` outside the trained range."""
        if self.extrapolation(velocity)["outside"] is True:
            lo, hi = self.velocity_range
            warnings.warn(f"velocity {velocity} mm/s is outside the trained range [{lo}, {hi}] mm/s: the "
                          "surrogate extrapolates", ExtrapolationWarning, stacklevel=_outside_toolkit())
        y = self.predict_items(item_features(inputs, [velocity], self.config.features))
        return np.moveaxis(y[..., :3], 0, 1), np.moveaxis(y[..., 3], 0, 1)

    def inference_ms_per_frame(self, db: ImpactDatabase, repeats: int = 3) -> float:
        """Wall time (ms) to predict the whole face, divided by the number of frames; best of
        ``repeats`` (one thread unless the caller raised it)."""
        best = np.inf
        for _ in range(repeats):
            t0 = time.perf_counter()
            self.predict(float(db.velocities[0]), db.inputs)
            best = min(best, time.perf_counter() - t0)
        return 1000.0 * best / db.times.size


@dataclass(frozen=True, eq=False)
class Prediction:
    """A surrogate's whole-face prediction of the database's scene at one velocity.

    Attributes: ``scene`` (the Scene predicted for), ``face`` (Mesh), ``times`` (F,) s,
    ``displacement`` (F, N, 3) mm, ``von_mises`` (F, N) MPa, ``wall_time_s``, ``extrapolation``
    (:meth:`Surrogate.extrapolation` of the velocity; also in the summary), ``checks`` (the
    values of :func:`toolkit.impact.checks.answer_checks`, ``passed`` False for an answer that
    must not be given as it is; also in the summary).
    """

    scene: Scene
    face: Mesh
    times: np.ndarray
    displacement: np.ndarray
    von_mises: np.ndarray
    wall_time_s: float
    config: str
    extrapolation: dict | None = None
    checks: dict | None = None

    def summary(self) -> dict:
        """The keys of :meth:`toolkit.impact.simulate.ImpactResult.summary` that a prediction
        computes (what only an FE run knows, its steps, energies and contact, is left out), with
        ``predicted_by`` and ``extrapolation``."""
        mag = np.linalg.norm(self.displacement, axis=2)
        return {"face_nodes": self.face.n_points, "face_elements": self.face.n_cells,
                "element": self.face.volume_type,
                "ball": "rigid" if self.scene.ball.rigid else "deformable",
                "velocity_mm_s": float(self.scene.ball.velocity),
                "wall_time_s": self.wall_time_s, "max_displacement_mm": float(mag.max()),
                "max_von_mises_mpa": float(self.von_mises.max()), "predicted_by": f"{MODEL_KIND} ({self.config})",
                "extrapolation": self.extrapolation,
                **({} if self.checks is None else {"checks": {"answer": self.checks}})}

    def write(self, out: str | os.PathLike, preview: bool = True, point_data: dict | None = None) -> Path:
        """``face.xdmf`` (+ .h5; point data ``displacement`` mm, ``von_mises`` MPa per frame, and
        each ``point_data`` field ``(F, N, ...)`` of its frames),
        ``summary.json``, ``scene.toml`` (run the FE of the same case with
        ``toolkit impact simulate --scene scene.toml``) and, with ``preview``, ``preview.png`` of
        the last frame (as :func:`toolkit.impact.simulate.simulate` draws it)."""


        out = Path(out)
        out.mkdir(parents=True, exist_ok=True)
        with TimeSeriesWriter(out / "face.xdmf", self.face.without_fields()) as w:
            for k, t in enumerate(self.times):
                w.append(float(t), displacement=self.displacement[k], von_mises=self.von_mises[k],
                         **{name: np.asarray(v)[k] for name, v in (point_data or {}).items()})
        write_summary(out / "summary.json", {"status": "finished", **self.summary()})
        self.scene.write(out / "scene.toml")
        if preview:
            ball = None
            if self.scene.ball.rigid:
                d = np.asarray(self.scene.ball.direction, dtype=float)
                centre = ball_start(self.scene, self.face.points[self.face.node_set("skin")])
                ball = (centre + self.scene.ball.velocity * d * float(self.times[-1]), self.scene.ball.radius)
            write_preview(out / "preview.png", self.face, self.displacement[-1], self.von_mises[-1],
                          float(self.times[-1]), ball)
        return out


def predict_scene(surrogate: Surrogate, velocity: float) -> Prediction:
    """Predict the training database's scene at ``velocity`` mm/s on its face (rebuilt from the
    scene, and refused if it is not the face the model was trained on), with the answer's checks
    (:func:`toolkit.impact.checks.answer_checks`; the prediction's ``checks``)."""

    t0 = time.perf_counter()
    sig = surrogate.bundle.data
    scene = Scene.from_dict(sig["scene"]).with_ball(velocity=float(velocity))
    face = face_mesh(scene)
    if points_fingerprint(face.points) != sig["mesh_checksum"]:
        raise ValueError(f"the scene's face ({face.n_points} nodes) is not the one the model was trained on "
                         f"({sig['n_nodes']} nodes, checksum {sig['mesh_checksum']})")
    times = np.asarray(sig["times_s"], dtype=float)
    inputs = SceneInputs.from_scene(scene, face, times)
    u, vm = surrogate.predict(float(velocity), inputs)
    checks = answer_checks(face, u, vm, np.flatnonzero(inputs.fixed))
    return Prediction(scene, face, times, u, vm, time.perf_counter() - t0, surrogate.config.name,
                      surrogate.extrapolation(float(velocity)), checks)


def _outside_toolkit() -> int:
    """The ``stacklevel`` of the first caller outside the toolkit package (a warning then names
    the user's line, not an internal one)."""
    import sys

    root = str(Path(__file__).resolve().parents[1])
    frame: FrameType | None = sys._getframe(1)
    level = 1
    while frame is not None and str(Path(frame.f_code.co_filename).resolve()).startswith(root):
        frame, level = frame.f_back, level + 1
    return level
