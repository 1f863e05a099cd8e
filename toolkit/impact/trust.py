"""Impact surrogate answers within a tolerance: a calibrated error estimate per node and frame,
an out-of-distribution check of the velocity and the scene, and the quasi-static finite
elements when either says the surrogate may miss.

An answer's error is the 95th percentile, over all nodes and all frames, of its nodal
displacement error (mm) against the FE of the same scene at the same velocity.
:func:`calibrate_surrogate` measures, on whole simulations at velocities the model never trained
on, the ratio of that error to a *scale* the model computes without the FE:

- ``interpolation`` (default): the distance, per node and frame, between the network's
  prediction and the linear interpolation in velocity of the two nearest training simulations
  (beyond the training velocities, the extrapolation of the two outermost), plus 0.01 mm. The
  interpolation is exact at the training velocities and follows them between; where the
  network departs from it, one of the two misses;
- ``constant``: 1 mm for every node and frame (plain split-conformal: one bound for every
  answer).

Split-conformal calibration (:mod:`toolkit.common.training.conformal`) turns the ratios into a
factor whose bound holds at the stated coverage for a new velocity exchangeable with the
calibration ones. Inputs unlike them void the guarantee, so :func:`out_of_distribution` checks
the velocity against the training range and the scene against the training scene (the aim,
the ball, the face, the material, the duration), and :func:`answer` runs the FE for such
inputs whatever the estimate says.

The FE that answers is the scene's quasi-static path (``Fidelity.integrator = "quasi-static"``),
the cheaper of the two integrators: for a database built quasi-static
(``toolkit impact database --integrator quasi-static``) it is the FE the model learned, and for a
database of explicit runs it differs from it by the integrators' difference, which
``benchmarks/impact_ladder.py`` measures.

The calibration is saved beside the model (``calibration.json`` and ``calibration.npz``).
Units: mm, s, mm/s, MPa.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common.config_diff import differences, jsonable
from toolkit.common.errors import AnswerError
from toolkit.common.meshes.fingerprint import points_fingerprint
from toolkit.common.training.conformal import (
    ConformalBound,
    calibrate,
    load_calibration,
    min_calibration_cases,
    save_calibration,
)
from toolkit.common.training.decision import check_tolerance, decide
from toolkit.impact.checks import answer_checks
from toolkit.impact.database import ImpactDatabase, SceneInputs, _scene_config, load_database
from toolkit.impact.scene import Scene
from toolkit.impact.simulate import face_mesh, simulate, write_summary
from toolkit.impact.surrogate import ExtrapolationWarning, Prediction

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.impact.simulate import ImpactResult
    from toolkit.impact.surrogate import Prediction

__all__ = ["SCALES", "Calibration", "calibrate_surrogate", "estimate", "out_of_distribution", "answer",
           "answer_error", "TrustedAnswer"]

#: how the error estimate's scale is computed (see the module)
SCALES = ("interpolation", "constant")
#: mm added to the disagreement so that a scale is never zero
SCALE_FLOOR_MM = 0.01
#: the integrator of the FE fallback: quasi-static load steps
FALLBACK_INTEGRATOR = "quasi-static"


def answer_error(predicted: np.ndarray, reference: np.ndarray) -> float:
    """An answer's error: the 95th percentile over nodes and frames of ``|predicted - reference|``
    (mm); both ``(F, N, 3)`` mm."""
    return float(np.percentile(np.linalg.norm(np.asarray(predicted, dtype=np.float64)
                                              - np.asarray(reference, dtype=np.float64), axis=-1), 95))


def _case_scale(node_scale: np.ndarray) -> float:
    return float(np.percentile(node_scale, 95))


@dataclass(frozen=True, eq=False)
class Calibration:
    """An impact surrogate's calibrated error estimate and what it was calibrated on.

    scale : one of :data:`SCALES`
    bound : ConformalBound (its ``factor`` times an answer's scale bounds that answer's error)
    train_velocities : (S,) mm/s, sorted, the velocities the model trained on
    fields : (S, F, N, 3) float32 mm, the FE displacement at those velocities (``interpolation``),
        else None
    cases : per calibration velocity: ``velocity_mm_s``, ``error_mm``, ``scale_mm``, ``fe_s``,
        ``surrogate_s``
    source : the databases and how their simulations were chosen
    """

    scale: str
    bound: ConformalBound
    train_velocities: np.ndarray
    fields: np.ndarray | None
    cases: list = field(default_factory=list)
    source: dict = field(default_factory=dict)

    def save(self, directory) -> Path:
        """Write ``calibration.json`` and ``calibration.npz`` into the model directory."""
        arrays = {"train_velocities": self.train_velocities}
        if self.fields is not None:
            arrays["fields"] = self.fields
        meta = {"kind": "toolkit.impact.trust", "scale": self.scale, "bound": self.bound.to_dict(),
                "cases": self.cases, "source": self.source}
        return save_calibration(directory, meta, arrays)

    @classmethod
    def load(cls, directory) -> Calibration:
        """Read the calibration of a model directory (FileNotFoundError naming the command that
        makes one)."""
        meta, arrays = load_calibration(directory, "toolkit impact calibrate")
        if meta.get("kind") != "toolkit.impact.trust":
            raise ValueError(f"{directory}/calibration.json is not an impact calibration (kind {meta.get('kind')!r})")
        return cls(meta["scale"], ConformalBound.from_dict(meta["bound"]), arrays["train_velocities"],
                   arrays.get("fields"), meta["cases"], meta["source"])

    def at(self, coverage: float) -> Calibration:
        """The same calibration with its bound at another coverage."""
        return replace(self, bound=self.bound.at(coverage))

    def interpolate(self, velocity: float) -> np.ndarray:
        """The training simulations' displacement interpolated linearly in ``velocity`` (mm/s)
        between its two nearest training velocities (extrapolated from the two outermost
        beyond them): ``(F, N, 3)`` mm."""
        if self.fields is None:
            raise ValueError(f"a {self.scale!r} calibration keeps no training fields")
        v = self.train_velocities
        i = int(np.clip(np.searchsorted(v, velocity) - 1, 0, v.size - 2))
        w = (float(velocity) - v[i]) / (v[i + 1] - v[i])
        return (1.0 - w) * self.fields[i].astype(np.float64) + w * self.fields[i + 1].astype(np.float64)


def _scale_field(calibration: Calibration, displacement: np.ndarray, velocity: float) -> np.ndarray:
    """Per node and frame scale ``(F, N)`` mm of a predicted displacement ``(F, N, 3)``."""
    if calibration.scale == "constant":
        return np.ones(displacement.shape[:2])
    return np.linalg.norm(displacement - calibration.interpolate(velocity), axis=-1) + SCALE_FLOOR_MM


def _train_velocities(model) -> np.ndarray:
    v = model.bundle.extra.get("split", {}).get("train_velocities")
    if not v:
        raise ValueError(f"{getattr(model.bundle, 'directory', 'the model')} does not record its training velocities: "
                         "retrain it with `toolkit impact train`")
    return np.sort(np.asarray(v, dtype=np.float64))


def _seen(velocities: np.ndarray, train: np.ndarray) -> np.ndarray:
    return np.isclose(velocities[:, None], train[None, :], rtol=0, atol=1e-9).any(axis=1)


def calibrate_surrogate(model, database, *, coverage: float = 0.9, scale: str = "interpolation", training=None,
                     progress: bool = True) -> Calibration:
    """Calibrate ``model``'s error estimate on the simulations of ``database`` at velocities the
    model never trained on.

    Parameters
    ----------
    model : :class:`~toolkit.impact.surrogate.Surrogate`
    database : path of an impact database or an ImpactDatabase of the model's scene and face: its
        simulations at velocities outside the model's training velocities are the calibration
        cases (the held-out velocities of the training database, or a database built for it)
    coverage : probability the bound holds for a new velocity like these (at least
        :func:`~toolkit.common.training.conformal.min_calibration_cases` velocities are needed:
        9 for 90 %, 19 for 95 %)
    scale : one of :data:`SCALES`
    training : the database the model was trained on (default ``database``): the
        ``interpolation`` scale keeps its simulations at the training velocities
    progress : tqdm over the velocities

    Returns
    -------
    Calibration (not saved: ``.save(model_directory)``)
    """
    from tqdm import tqdm


    if scale not in SCALES:
        raise ValueError(f"scale = {scale!r}; expected one of {SCALES}")
    db = database if isinstance(database, ImpactDatabase) else load_database(database)
    model.check_database(db)
    train_db = db if training is None else (training if isinstance(training, ImpactDatabase)
                                            else load_database(training))
    if train_db is not db:
        model.check_database(train_db)
    train_v = _train_velocities(model)
    cases_i = np.flatnonzero(~_seen(db.velocities, train_v))
    need = min_calibration_cases(coverage)
    if cases_i.size < need:
        raise ValueError(f"{db.path} holds {cases_i.size} simulation(s) at velocities the model did not train on; a "
                         f"bound at {coverage:.0%} needs at least {need}: build a calibration database at other "
                         "velocities of the same scene (`toolkit impact database --velocities ... --out CAL.h5`, then "
                         "--data CAL.h5 --train-data TRAIN.h5) or lower --coverage")
    fields = None
    if scale == "interpolation":
        have = _seen(train_v, train_db.velocities)
        if not have.all():
            raise ValueError(f"{train_db.path} lacks the training simulations at {train_v[~have].tolist()} mm/s: give "
                             "the database the model was trained on (command line: --train-data DB.h5)")
        rows = [int(np.flatnonzero(np.isclose(train_db.velocities, v, rtol=0, atol=1e-9))[0]) for v in train_v]
        fields = np.asarray(train_db.displacement[rows], dtype=np.float32)
    partial = Calibration(scale, ConformalBound(coverage, 1.0, (1.0,)), train_v, fields)
    fe_s = db.index["wall_time_s"].to_numpy(float) if "wall_time_s" in db.index else np.full(db.velocities.size, np.nan)
    cases = []
    for i in tqdm(cases_i, desc="calibration velocities", disable=not progress):
        v = float(db.velocities[i])
        t0 = time.perf_counter()
        u, _ = model.predict(v, db.inputs)
        node = _scale_field(partial, u, v)
        cases.append({"velocity_mm_s": v, "error_mm": answer_error(u, db.displacement[i]),
                      "scale_mm": _case_scale(node), "surrogate_s": time.perf_counter() - t0,
                      "fe_s": float(fe_s[i])})
    bound = calibrate([c["error_mm"] for c in cases], [c["scale_mm"] for c in cases], coverage)
    return replace(partial, bound=bound, cases=cases,
                   source={"database": str(Path(db.path).resolve()),
                           "velocities": "every simulation at a velocity the model did not train on",
                           "training_database": str(Path(train_db.path).resolve())})


def estimate(calibration: Calibration, displacement: np.ndarray, velocity: float) -> dict:
    """The calibrated error estimate of a predicted displacement ``(F, N, 3)`` mm at ``velocity``.

    Returns ``{"bound_mm", "coverage", "scale", "scale_mm", "node_mm"}``: ``bound_mm`` bounds
    the answer's error (95th percentile of the nodal error over nodes and frames) with
    probability ``coverage`` for a velocity like the calibration ones; ``node_mm`` ``(F, N)`` is
    the estimate per frame and node (the factor times each one's scale).
    """
    node = _scale_field(calibration, np.asarray(displacement, dtype=np.float64), velocity)
    s = _case_scale(node)
    return {"bound_mm": float(calibration.bound.bound(s)), "coverage": calibration.bound.coverage,
            "scale": calibration.scale, "scale_mm": s, "node_mm": calibration.bound.bound(node)}


#: scene settings that do not change what the surrogate learned (the FE's integrator and its options)
_IGNORED = ("fidelity.integrator", "fidelity.load_steps", "fidelity.tolerance", "fidelity.safety", "fidelity.dt",
            "fidelity.allow_unstable_dt", "fidelity.mass_scaling")


def out_of_distribution(model, scene) -> dict:
    """Whether ``scene`` (a :class:`~toolkit.impact.scene.Scene`) lies beyond what ``model`` learned.

    Returns ``{"outside": bool, "reasons": [str], "velocity": extrapolation dict with
    ``nearest_training_mm_s`` (the distance to the nearest training velocity), "scene":
    {"differences": [[key, trained, asked], ...]}}``. The scene differs when any setting but
    the ball's velocity and the integrator's options differs from the training database's:
    another aim, ball, face, support, material, duration or frames.
    """

    reasons = []
    v = float(scene.ball.velocity)
    ex = model.extrapolation(v)
    train = _train_velocities(model)
    ex["nearest_training_mm_s"] = float(np.min(np.abs(train - v)))
    if ex["outside"] is True:
        lo, hi = model.velocity_range
        reasons.append(f"velocity: {v:g} mm/s is outside the training velocities [{lo:g}, {hi:g}] mm/s")
    diff = differences(model.bundle.data["scene"], _scene_config(scene), ignore=_IGNORED)
    if diff:
        reasons.append("scene: " + ", ".join(f"{k} {b!r} (trained: {a!r})" for k, a, b in diff[:4])
                       + (f" and {len(diff) - 4} more" if len(diff) > 4 else ""))
    return {"outside": bool(reasons), "reasons": reasons, "velocity": ex,
            "scene": {"differences": [[k, a, b] for k, a, b in diff]}}


@dataclass(frozen=True, eq=False)
class TrustedAnswer:
    """An impact answer within a tolerance: the surrogate's prediction or the FE's result.

    result : :class:`~toolkit.impact.surrogate.Prediction` (``answered_by == "surrogate"``) or
        :class:`~toolkit.impact.simulate.ImpactResult` (``"fe"``)
    answered_by : ``surrogate`` or ``fe``
    reason : why (one line)
    tolerance_mm : the tolerance asked
    estimate : :func:`estimate` of the surrogate's prediction (``node_mm`` left out of the summary)
    ood : :func:`out_of_distribution`
    seconds : ``surrogate``, ``estimate``, ``checks`` (the surrogate answer's, made only when it is
        within the tolerance and in distribution), ``fe`` (0 when not run), ``total``
    fe_integrator : the FE's integrator (``quasi-static``)

    Construction checks a post-condition: :class:`~toolkit.common.errors.AnswerError` when the result's von Mises stress
    ``(F, N)`` MPa is negative or NaN anywhere (the surrogate clamps its stress at zero; the FE's
    is a square root averaged with positive weights).
    """

    result: Prediction | ImpactResult
    answered_by: str
    reason: str
    tolerance_mm: float
    estimate: dict
    ood: dict
    seconds: dict
    fe_integrator: str = FALLBACK_INTEGRATOR

    def __post_init__(self):
        vm = np.asarray(self.result.von_mises)
        bad = ~(vm >= 0.0)
        if bad.any():
            raise AnswerError(f"the {self.answered_by} answer has {int(bad.sum())} of {vm.size} node-frames with a "
                               f"negative or NaN von Mises stress (lowest {np.nanmin(vm, initial=np.inf):g} MPa); "
                               "expected >= 0 everywhere")

    @property
    def displacement(self) -> np.ndarray:
        """(F, N, 3) mm, whichever answered."""
        return self.result.displacement

    def write_summary(self, out) -> None:
        """``out/summary.json``: the result's summary with ``answer`` (atomically)."""

        write_summary(Path(out) / "summary.json", jsonable({"status": "finished", **self.summary()}))

    def summary(self) -> dict:
        est = {k: v for k, v in self.estimate.items() if k != "node_mm"}
        return {**self.result.summary(), "answer": {
            "answered_by": self.answered_by, "reason": self.reason, "tolerance_mm": self.tolerance_mm,
            "estimate": est, "out_of_distribution": self.ood, "seconds": self.seconds,
            "fe_integrator": self.fe_integrator}}


def answer(model, velocity: float | None, tolerance_mm: float, *, scene=None, calibration=None,
           coverage: float | None = None, out=None, progress: bool = False, preview: bool = True
           ) -> TrustedAnswer:
    """The surrogate's answer when its calibrated estimate is within ``tolerance_mm``, the
    inputs are like its training data and the answer passes its checks
    (:func:`toolkit.impact.checks.answer_checks`: no inverted element, held nodes held, no
    negative stress); otherwise the quasi-static FE of the same scene.

    Parameters
    ----------
    model : Surrogate (its directory must hold a calibration, or pass ``calibration``)
    velocity : ball velocity, mm/s (None: ``scene``'s)
    tolerance_mm : mm, > 0: the largest answer error (95th percentile of the nodal error over
        nodes and frames) accepted
    scene : the scene to answer (default the training database's at ``velocity``); it must be on
        the training face; another aim, ball or duration is out of distribution
    calibration : default :meth:`Calibration.load` of the model's directory
    coverage : the estimate's coverage (default the calibration's)
    out : folder to write the answer into (``face.xdmf`` with ``error_estimate`` per frame when
        the surrogate answers; ``toolkit impact simulate``'s files when the FE does; both with
        ``summary.json`` holding ``answer``)
    progress : tqdm over the FE's frames

    Raises ValueError for a tolerance that is not a positive number, before any computation.
    """

    tolerance_mm = check_tolerance(tolerance_mm, 1)
    calibration = calibration or Calibration.load(model.directory)
    if coverage is not None:
        calibration = calibration.at(coverage)
    sig = model.bundle.data
    base = Scene.from_dict(sig["scene"]) if scene is None else scene
    scene = base if velocity is None else base.with_ball(velocity=float(velocity))
    velocity = float(scene.ball.velocity)
    if out is not None:
        from toolkit.common.outputs import check_output_dir

        check_output_dir(out)
    t0 = time.perf_counter()
    seconds = {"surrogate": 0.0, "estimate": 0.0, "checks": 0.0, "fe": 0.0}
    ood = out_of_distribution(model, scene)
    face = face_mesh(scene)
    est, pred = {}, None
    if face.n_points == sig["n_nodes"] and points_fingerprint(face.points) == sig["mesh_checksum"]:
        times = np.asarray(sig["times_s"], dtype=float)
        inputs = SceneInputs.from_scene(scene, face, times)
        u, vm = _quiet_predict(model, velocity, inputs)
        seconds["surrogate"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        est = estimate(calibration, u, velocity)
        seconds["estimate"] = time.perf_counter() - t1
        pred = Prediction(scene, face, times, u, vm, seconds["surrogate"], model.config.name, ood["velocity"])

    def checks():  # made only for an answer that would otherwise be given
        nonlocal pred
        pred = _checked(pred, inputs, seconds)
        return pred.checks

    decision = decide(tolerance_mm, ood, est, checks, no_estimate="another face than the model's")
    if decision.surrogate:
        assert pred is not None  # an answer given has been predicted
        seconds["total"] = time.perf_counter() - t0
        ans = TrustedAnswer(pred, "surrogate", decision.reason, tolerance_mm, est, ood, seconds)
        if out is not None:
            pred.write(out, preview=preview, point_data={"error_estimate": est["node_mm"]})
            ans.write_summary(out)
        return ans
    t1 = time.perf_counter()
    # the explicit-only options (a database built explicit) do not apply to the quasi-static FE
    fe_scene = scene.with_fidelity(integrator=FALLBACK_INTEGRATOR, mass_scaling=1.0, dt=None)
    fe = simulate(fe_scene, out=out, progress=progress, preview=preview)
    seconds["fe"] = time.perf_counter() - t1
    seconds["total"] = time.perf_counter() - t0
    ans = TrustedAnswer(fe, "fe", decision.reason, tolerance_mm, est, ood, seconds)
    if out is not None:
        ans.write_summary(out)
    return ans


def _checked(pred, inputs, seconds: dict):
    """``pred`` with its answer checks (:func:`~toolkit.impact.checks.answer_checks`), their time in
    ``seconds["checks"]``."""
    checks = answer_checks(pred.face, pred.displacement, pred.von_mises, np.flatnonzero(inputs.fixed))
    seconds["checks"] = checks["seconds"]
    return replace(pred, checks=checks)


def _quiet_predict(model, velocity, inputs):
    """The prediction without the ExtrapolationWarning (the answer's out-of-distribution check
    records the velocity's distance to the training ones)."""
    import warnings


    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ExtrapolationWarning)
        return model.predict(velocity, inputs)
