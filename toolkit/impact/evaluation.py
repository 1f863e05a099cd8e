"""Scoring an impact surrogate against the FE database, and its figures.

The impact paper's metrics: RMSE and Pearson correlation between the FE and predicted
displacement (mm) and von Mises stress (MPa) over every test item and frame; here also
normalised by the test set's peak (NRMSE: displacement RMSE over the largest displacement
magnitude, stress RMSE over the largest von Mises stress; the ``*_nrmse`` keys are fractions,
0.01 = 1 % of the peak), the displacement magnitude's
RMSE/Pearson (the impact paper predicts one output, likely the magnitude), the training time, the
inference time per whole-face frame and the FE time per frame from the database.

Figures (matplotlib, PNG): FE against predicted time series at chosen nodes, and
front-view field maps (skin-side nodes projected on the x-z plane) of FE, prediction and
error at chosen frames.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from toolkit.common.analysis import metrics
from toolkit.common.meshes.io import atomic_path
from toolkit.common.training.evaluation import Evaluation
from toolkit.impact.database import ImpactDatabase, load_database
from toolkit.impact.surrogate import Surrogate, item_features, item_targets, split_items

__all__ = ["Evaluation", "evaluate_surrogate", "plot_time_series", "plot_fields", "write_evaluation",
           "check_figure_choices"]


def field_metrics(predicted: np.ndarray, truth: np.ndarray) -> dict:
    """The impact paper's metrics (and NRMSE) of ``(..., 4)`` arrays of ux, uy, uz (mm) and von Mises (MPa).

    ``*_rmse_mm``/``*_rmse_mpa`` in mm/MPa; ``*_pearson`` in [-1, 1]; ``displacement_nrmse`` and
    ``von_mises_nrmse`` are fractions of the test set's peak (0.01 = 1 %; print them with ``:.2%``)."""
    up, ut = predicted[..., :3], truth[..., :3]
    vp, vt = predicted[..., 3], truth[..., 3]
    mag_p, mag_t = np.linalg.norm(up, axis=-1), np.linalg.norm(ut, axis=-1)
    return {
        "displacement_rmse_mm": metrics.rmse(up, ut),
        "displacement_pearson": metrics.pearson(up, ut),
        "displacement_nrmse": metrics.nrmse(up, ut, peak=float(mag_t.max())),
        "displacement_magnitude_rmse_mm": metrics.rmse(mag_p, mag_t),
        "displacement_magnitude_pearson": metrics.pearson(mag_p, mag_t),
        "von_mises_rmse_mpa": metrics.rmse(vp, vt),
        "von_mises_pearson": metrics.pearson(vp, vt),
        "von_mises_nrmse": metrics.nrmse(vp, vt),
        "peak_displacement_mm": float(mag_t.max()),
        "peak_von_mises_mpa": float(vt.max()),
    }


def evaluate_surrogate(surrogate: Surrogate, database: ImpactDatabase | str | os.PathLike, *,
                       split: str | None = None) -> Evaluation:
    """Score ``surrogate`` on the test items of ``split`` (default: the split it was trained
    with, rebuilt from its seed) of ``database``, which must be the database it was trained on
    (same face, scene and frames; refused otherwise).

    Returns an :class:`~toolkit.common.training.evaluation.Evaluation` (``per_sample`` None)."""
    db = load_database(database) if not isinstance(database, ImpactDatabase) else database
    surrogate.check_database(db)
    spec = surrogate.bundle.extra["split"]
    split = split or spec["kind"]
    items = split_items(db, split, int(spec["seed"]))["test"]
    x = item_features(db.inputs, db.velocities, surrogate.config.features)[items]
    truth = item_targets(db)[items].astype(np.float64)
    predicted = surrogate.predict_items(x)
    m = field_metrics(predicted, truth)
    extra = surrogate.bundle.extra
    fe = db.index["fe_ms_per_frame"].to_numpy(dtype=float) if "fe_ms_per_frame" in db.index else np.array([np.nan])
    inference = surrogate.inference_ms_per_frame(db)
    m.update({
        "config": surrogate.config.name,
        "split": split,
        "test_velocities_mm_s": sorted(set(db.velocities[items // db.n_nodes].tolist())),
        "n_test_items": int(items.size),
        "n_train_items": int(extra.get("n_train_items", 0)),
        "frames": int(db.times.size),
        "train_seconds": float(extra["train_seconds"]),
        "epochs_run": int(extra.get("epochs_run", 0)),
        "best_epoch": int(extra.get("best_epoch", 0)),
        "stopped": extra.get("stopped"),
        "inference_ms": inference,
        "fe_ms_per_frame": float(np.median(fe)),
        "speedup_vs_fe": float(np.median(fe)) / inference,
    })
    return Evaluation(m, items, predicted, truth)


def check_figure_choices(db: ImpactDatabase, nodes=None, frames=None, ev: Evaluation | None = None) -> None:
    """Refuse figure choices the database cannot show, before anything is computed or written:
    ``nodes`` (node ids, for ``timeseries.png``) outside ``[0, n_nodes)``, ``frames`` (frame
    indices, for ``fields.png``) outside ``[0, n_frames)``, an empty list; with ``ev``, nodes that
    are not test items of the simulation the figures show."""
    for name, values, size, what in (("nodes", nodes, db.n_nodes, "node ids"),
                                     ("frames", frames, db.times.size, "frame indices")):
        if values is None:
            continue
        values = [int(v) for v in values]
        if not values:
            raise ValueError(f"{name} is an empty list; expected {what} in [0, {size - 1}] (or none: the default)")
        bad = [v for v in values if not 0 <= v < size]
        if bad:
            raise ValueError(f"{name} {bad} out of range: {db.path} has {size} {what.split()[0]}s, expected "
                             f"{what} in [0, {size - 1}]")
    if ev is not None and nodes is not None:
        sim = _chosen_sim(db, ev)
        test_nodes = set((ev.items[ev.items // db.n_nodes == sim] % db.n_nodes).tolist())
        missing = [int(n) for n in nodes if int(n) not in test_nodes]
        if missing:
            example = sorted(test_nodes)[:3]
            raise ValueError(f"nodes {missing} are not test items of the {db.velocities[sim]:g} mm/s simulation "
                             f"that timeseries.png shows; expected test nodes, e.g. {example}")


def _chosen_sim(db: ImpactDatabase, ev: Evaluation) -> int:
    """The fastest simulation that has test items."""
    sims = np.unique(ev.items // db.n_nodes)
    return int(sims[np.argmax(db.velocities[sims])])


def plot_time_series(db: ImpactDatabase, ev: Evaluation, path, nodes=None):
    """FE (solid) and predicted (dashed) displacement magnitude and von Mises stress over time at
    ``nodes`` (default: the test nodes of largest final displacement, largest stress, and median
    final displacement) of the fastest simulation with test items. Returns the Figure."""
    from matplotlib.figure import Figure

    sim = _chosen_sim(db, ev)
    mine = np.flatnonzero(ev.items // db.n_nodes == sim)
    node_of = ev.items[mine] % db.n_nodes
    mag = np.linalg.norm(ev.truth[mine, :, :3], axis=-1)
    if nodes is None:
        order = np.argsort(mag[:, -1])
        picks = [mine[order[-1]], mine[int(np.argmax(ev.truth[mine, :, 3].max(axis=1)))], mine[order[order.size // 2]]]
    else:
        lookup = {int(n): i for i, n in zip(mine, node_of)}
        missing = [n for n in nodes if int(n) not in lookup]
        if missing:
            raise ValueError(f"nodes {missing} are not test items of the {db.velocities[sim]} mm/s simulation")
        picks = [lookup[int(n)] for n in nodes]
    fig = Figure(figsize=(9.0, 2.6 * len(picks)), layout="constrained")
    axes = fig.subplots(len(picks), 2, squeeze=False)
    t = db.times
    for row, i in enumerate(picks):
        node = int(ev.items[i] % db.n_nodes)
        for col, (label, fe, pr) in enumerate((
                ("|u| (mm)", np.linalg.norm(ev.truth[i, :, :3], axis=-1),
                 np.linalg.norm(ev.predicted[i, :, :3], axis=-1)),
                ("von Mises (MPa)", ev.truth[i, :, 3], ev.predicted[i, :, 3]))):
            ax = axes[row, col]
            ax.plot(t, fe, "k-", label="FE")
            ax.plot(t, pr, "C1--", label=ev.metrics["config"])
            ax.set_ylabel(label)
            ax.set_title(f"node {node} at {db.velocities[sim]:g} mm/s", fontsize=9)
            ax.grid(alpha=0.3)
        axes[row, 0].legend(fontsize=8)
    for ax in axes[-1]:
        ax.set_xlabel("time (s)")
    _save(fig, path)
    return fig


def plot_fields(db: ImpactDatabase, surrogate: Surrogate, path, sim: int | None = None, frames=None):
    """Front-view maps (x-z, mm) of FE, predicted and |error| displacement magnitude and von Mises
    stress of the whole face at ``frames`` (default: the middle and the last) of simulation
    ``sim`` (default: the fastest held-out one, else the fastest); each panel is titled with that
    simulation's velocity and whether it is held out or a training velocity. Returns the Figure."""
    from matplotlib.figure import Figure

    if sim is None:
        cands = np.flatnonzero(db.held_out) if db.held_out.any() else np.arange(db.velocities.size)
        sim = int(cands[np.argmax(db.velocities[cands])])
    frames = [db.times.size // 2, db.times.size - 1] if frames is None else [int(f) for f in frames]
    u, vm = surrogate.predict(float(db.velocities[sim]), db.inputs)
    front = db.points[:, 1] > np.percentile(db.points[:, 1], 40)  # the anterior part, seen from the front
    x, z = db.points[front, 0], db.points[front, 2]
    speed = f"{db.velocities[sim]:g} mm/s ({'held out' if db.held_out[sim] else 'training velocity'})"
    fig = Figure(figsize=(11.0, 3.2 * 2 * len(frames)), layout="constrained")
    axes = fig.subplots(2 * len(frames), 3, squeeze=False)
    for k, f in enumerate(frames):
        for j, (name, fe, pr) in enumerate((
                ("|u| (mm)", np.linalg.norm(db.displacement[sim, f], axis=1), np.linalg.norm(u[f], axis=1)),
                ("von Mises (MPa)", db.von_mises[sim, f].astype(float), vm[f]))):
            row = 2 * k + j
            lim = (0.0, float(max(fe[front].max(), pr[front].max(), 1e-12)))
            for col, (title, values, vlim) in enumerate((("FE", fe, lim), ("predicted", pr, lim),
                                                         ("|error|", np.abs(pr - fe), None))):
                ax = axes[row, col]
                sc = ax.scatter(x, z, c=values[front], s=4, cmap="inferno" if col < 2 else "viridis",
                                vmin=None if vlim is None else vlim[0], vmax=None if vlim is None else vlim[1])
                fig.colorbar(sc, ax=ax, shrink=0.8, label=name)
                ax.set_title(f"{title}, {speed}, t = {db.times[f]:.3f} s", fontsize=9)
                ax.set_aspect("equal")
                ax.set_xlabel("x (mm)")
                ax.set_ylabel("z (mm)")
    _save(fig, path)
    return fig


def write_evaluation(ev: Evaluation, db: ImpactDatabase, surrogate: Surrogate, out: str | os.PathLike,
                     nodes=None, frames=None) -> Path:
    """Write ``metrics.json``, ``timeseries.png`` and ``fields.png`` to ``out``; both figures show
    the fastest simulation with test items of ``ev`` (one of ``test_velocities_mm_s``). ``nodes``
    and ``frames`` are checked (:func:`check_figure_choices`) before anything is written."""

    check_figure_choices(db, nodes, frames, ev)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_path(out / "metrics.json") as tmp:
        tmp.write_text(json.dumps(ev.metrics, indent=2))
    plot_time_series(db, ev, out / "timeseries.png", nodes=nodes)
    plot_fields(db, surrogate, out / "fields.png", sim=_chosen_sim(db, ev), frames=frames)
    return out


def _save(fig, path) -> None:

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format=path.suffix.lstrip(".") or "png")
