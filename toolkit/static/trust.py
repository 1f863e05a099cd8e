"""Static surrogate answers within a tolerance: a calibrated error estimate, an
out-of-distribution check, and the finite elements when either says the surrogate may miss.

An answer's error is the 95th percentile over all nodes of its nodal displacement error (mm)
against the FE of the same plan on the same face. :func:`calibrate_surrogate` measures, on
whole simulations of a database the model neither trained nor validated on, the ratio of that
error to a *scale* the model can compute without the FE:

- ``disagreement``: the 95th percentile over nodes of the distance between the network's
  prediction and the baseline's (below), plus 0.01 mm. Two models built differently seldom miss
  the same way; where they disagree, at least one is wrong;
- ``constant``: 1 mm for every plan (plain split-conformal: one bound for every answer).

The baseline is the face's linear response under the FE's boundary conditions
(:class:`~toolkit.static.sliding_response.SlidingResponse`: mucosa sliding, lips in contact) plus
a POD regression of what it misses on the plan's parameters
(:class:`~toolkit.static.baselines.LinearPlusPOD`), fit here on the simulations the model was
trained and validated on and run increment by increment like the FE.

Split-conformal calibration (:mod:`toolkit.common.training.conformal`) turns the ratios into a
factor whose bound holds at the stated coverage for a new plan exchangeable with the
calibration ones. Inputs unlike them void that guarantee, so :func:`out_of_distribution`
checks the inputs first (a plan beyond what the training database's sampler spans, a face mesh of
another topology or farther from every training subject than they lie from each other, another
material), and :func:`answer` runs the FE for such inputs whatever the estimate says.

Which answer is given (``answerer``) and with which scale: ``auto`` (default, for both)
calibrates the network's and the baseline's errors against each scale. :func:`answer` then takes,
for the tolerance asked, the pair whose expected time per answer over the calibration plans is
least (:meth:`Calibration.for_tolerance`: its time, plus the FE's for the share of plans its bound
would send to the FE); the calibration's own pair, for an estimate without a tolerance, is the
cheapest (the disagreement scale runs both models) among those whose bound, averaged over the
calibration plans, is within :data:`AUTO_BOUND_SLACK` of the narrowest. The bound given always
belongs to the answer given. ``network``, ``baseline`` and a named scale restrict the choice.
Either choice is made on the calibration plans themselves, so the coverage of the chosen pair is
that of the best of (at most) four calibrated bounds, slightly optimistic for few plans. On the
paper phantom subjects the baseline with the constant scale answers at the looser tolerances
(``benchmarks/surrogate_trust.py``); the network is then not run at all.

The calibration is saved beside the model (``calibration.json`` and ``calibration.npz``).
"""

from __future__ import annotations

import json
import time
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from toolkit.common.config_diff import jsonable
from toolkit.common.meshes.fingerprint import mesh_fingerprint
from toolkit.common.meshes.io import atomic_path
from toolkit.common.phantoms.phantom import FacePhantom
from toolkit.common.training.conformal import (
    ConformalBound,
    calibrate,
    load_calibration,
    min_calibration_cases,
    save_calibration,
)
from toolkit.common.training.decision import check_tolerance, decide
from toolkit.common.training.extrapolation import describe_extrapolation
from toolkit.static.baselines import LinearPlusPOD, PODRegression
from toolkit.static.checks import with_answer_checks
from toolkit.static.database import PLAN_FEATURES, DatabaseConfig, StaticDatabase, plan_features
from toolkit.static.simulate import IncrementReport, face_mesh_and_segments, simulate
from toolkit.static.surrogate import (
    PLAN_PARAMETERS,
    PlanPrediction,
    _simulation_identities,
    check_database,
    evaluation_keys,
    plan_extrapolation,
    training_hull,
    with_exact_attachment,
)
from toolkit.static.surrogate import arch_nodes as surrogate_arch_nodes

if TYPE_CHECKING:  # pragma: no cover
    from toolkit.static.baselines import LinearPlusPOD
    from toolkit.static.simulate import SimulationResult

__all__ = ["SCALES", "ANSWERERS", "BASELINE", "Calibration", "calibrate_surrogate", "baseline_prediction", "estimate",
           "out_of_distribution", "answer", "TrustedAnswer"]

#: how the error estimate's scale is computed (see the module)
SCALES = ("disagreement", "constant")
#: which answer a calibration bounds: the network's, the baseline's, or the one with the smaller factor
ANSWERERS = ("auto", "network", "baseline")
#: the linear part of the baseline a calibration's residual regression is fit on
#: (:class:`~toolkit.static.sliding_response.SlidingResponse`)
BASELINE = "sliding response"
#: ``auto`` keeps the cheapest scale and answerer whose mean bound over the calibration plans is
#: within this factor of the narrowest: a conformal factor over tens of plans is an order
#: statistic whose sampling spread is wider than that
AUTO_BOUND_SLACK = 1.1
#: mm added to the disagreement so that a scale is never zero
SCALE_FLOOR_MM = 0.01
#: mm: a face farther (RMS over nodes) from every training subject than they lie from each other,
#: and at least this far, or with a node farther than this outside the box (per coordinate) its
#: training subjects span, is another shape
MIN_SHAPE_SPREAD_MM = 1.0


def answer_error(predicted: np.ndarray, reference: np.ndarray) -> float:
    """An answer's error: the 95th percentile over nodes of ``|predicted - reference|`` (mm);
    both ``(n, 3)`` mm."""
    return float(np.percentile(np.linalg.norm(np.asarray(predicted) - np.asarray(reference), axis=1), 95))


@dataclass(frozen=True, eq=False)
class Calibration:
    """A surrogate's calibrated error estimate and what it was calibrated on.

    scale : one of :data:`SCALES`
    bound : ConformalBound (its ``factor`` times a plan's scale bounds the error of the
        ``answerer``'s answer)
    residual : LinearPlusPOD, the regression of what the sliding response misses (the baseline's
        second part)
    train_plans : (m, 12) the plan parameters (last increment) of the simulations the model saw
    plan_ranges : parameter -> [min, max] over them (the scale of the distance to the nearest one)
    plan_hull : parameter -> [min, max] the training database's sampler spans
        (:func:`~toolkit.static.plan.sampling_hull` of its mode and jaw-closing bound)
    arch_nodes : (k,) int, the training topology's nodes of the dental arch
        (:func:`~toolkit.static.plan.dental_arch`), for the jaw closing of a plan
    subjects : (s, n, 3) mm, the training subjects' pre-operative points
    shape_spread_mm : the largest RMS distance between two training subjects (at least
        :data:`MIN_SHAPE_SPREAD_MM`)
    material : the training database's material
    cases : per calibration plan: ``key``, ``error_mm`` (the network's), ``baseline_error_mm``,
        ``scale_mm``, ``fe_s``, ``surrogate_s``
    source : database path and how its plans were chosen
    answerer : ``network`` or ``baseline``, whose answer the bound is for
    bounds : answerer -> its ConformalBound (both, for the record)
    candidates : the ``(scale, answerer)`` pairs :meth:`for_tolerance` chooses among (those the
        calibration was asked for)
    """

    scale: str
    bound: ConformalBound
    residual: LinearPlusPOD | None
    train_plans: np.ndarray
    plan_ranges: dict
    subjects: np.ndarray
    shape_spread_mm: float
    material: str
    cases: list = field(default_factory=list)
    source: dict = field(default_factory=dict)
    answerer: str = "network"
    bounds: dict = field(default_factory=dict)
    plan_hull: dict = field(default_factory=dict)
    arch_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    candidates: tuple = ()

    def save(self, directory) -> Path:
        """Write ``calibration.json`` and ``calibration.npz`` into the model directory."""
        arrays = {"train_plans": self.train_plans, "subjects": self.subjects, "arch_nodes": self.arch_nodes}
        if self.residual is not None:
            r = self.residual.residual
            arrays.update(mean=r.mean, modes=r.modes, coef=r.coef, x_scale=r.x_scale,
                          energy=np.array(r.energy))
        meta = {"scale": self.scale, "bound": self.bound.to_dict(), "plan_ranges": self.plan_ranges,
                "shape_spread_mm": self.shape_spread_mm, "material": self.material, "cases": self.cases,
                "source": self.source, "answerer": self.answerer,
                "bounds": {k: b.to_dict() for k, b in self.bounds.items()}, "baseline": BASELINE,
                "plan_hull": self.plan_hull, "candidates": [list(c) for c in self.candidates]}
        return save_calibration(directory, meta, arrays)

    @classmethod
    def load(cls, directory) -> Calibration:
        """Read the calibration of a model directory (FileNotFoundError naming the command that
        makes one; ValueError, naming it too, for a calibration written by an earlier version:
        a baseline on another linear part, or no record of what the training plans span)."""

        meta, arrays = load_calibration(directory, "toolkit static calibrate")
        missing = [what for what, ok in (
            (f"its baseline was fit on the influence matrix (mucosa and lips free), not on the {BASELINE}",
             meta.get("baseline") == BASELINE),
            ("it does not record what the training plans span (plan_hull) or its candidate answers",
             "plan_hull" in meta and "candidates" in meta and "arch_nodes" in arrays)) if not ok]
        if missing:
            raise ValueError(f"{Path(directory) / 'calibration.json'} was written by an earlier version: "
                             f"{'; '.join(missing)}; calibrate again: "
                             f"toolkit static calibrate --model {directory} --data DB.h5")
        residual = None
        if "modes" in arrays:
            residual = LinearPlusPOD(PODRegression(arrays["mean"], arrays["modes"], arrays["coef"],
                                                   arrays["x_scale"], float(arrays["energy"])))
        return cls(meta["scale"], ConformalBound.from_dict(meta["bound"]), residual, arrays["train_plans"],
                   meta["plan_ranges"], arrays["subjects"], float(meta["shape_spread_mm"]), meta["material"],
                   meta["cases"], meta["source"], meta.get("answerer", "network"),
                   {k: ConformalBound.from_dict(b) for k, b in meta.get("bounds", {}).items()},
                   meta["plan_hull"], arrays["arch_nodes"].astype(np.int64),
                   tuple(tuple(c) for c in meta["candidates"]))

    def at(self, coverage: float) -> Calibration:
        """The same calibration with its bound at another coverage."""
        return replace(self, bound=self.bound.at(coverage), bounds={k: b.at(coverage) for k, b in self.bounds.items()})

    def for_tolerance(self, tolerance_mm: float) -> Calibration:
        """The calibration whose scale, answerer and bound are those of its :attr:`candidates`
        with the least mean seconds per answer over the calibration plans at ``tolerance_mm``
        (mm): the pair's time on each plan, plus the FE's on the plans its bound, at this
        calibration's coverage, would leave to the FE (ties: the narrower mean bound); itself
        when it has one candidate."""
        if len(self.candidates) < 2:
            return self
        by_scale = {s: (_case_scales(self.cases, s), _bounds(self.cases, _case_scales(self.cases, s),
                                                            self.bound.coverage))
                    for s in {s for s, _ in self.candidates}}
        fe = np.array([c["fe_s"] for c in self.cases])

        def rank(pair):
            scales, bounds = by_scale[pair[0]]
            per_plan = bounds[pair[1]].bound(scales)
            own = np.array([_pair_seconds(c, *pair) for c in self.cases])
            return float(np.mean(own + np.where(per_plan > tolerance_mm, fe, 0.0))), float(np.mean(per_plan))

        scale, answerer = min(self.candidates, key=rank)
        bounds = by_scale[scale][1]
        return replace(self, scale=scale, answerer=answerer, bound=bounds[answerer], bounds=bounds)


def _baseline_trajectory(model, residual, face, plan, segments=None):
    """The face's SlidingResponse, the baseline's cumulative displacement ``(increments + 1, n, 3)``
    mm and each increment's bone motion ``(increments, n, 3)`` mm (see :func:`baseline_prediction`)."""

    increments = DatabaseConfig(**model.bundle.data["database"]).increments
    response = model.sliding_response(face, segments)
    with warnings.catch_warnings():  # the plan warned of its range where it was built
        warnings.simplefilter("ignore")
        params = plan_features(plan, increments)
    return (response, *response.trajectory(plan, increments, residual.residual.predict(params)))


def baseline_prediction(model, residual, face, plan, segments=None):
    """The sliding response + POD residual baseline's answer to ``plan`` on ``face`` (as for
    :meth:`~toolkit.static.surrogate.Surrogate.predict_plan`): the face's sliding response
    (:meth:`~toolkit.static.surrogate.Surrogate.sliding_response`) plus ``residual``'s regression on
    the plan, increment by increment along the training database's increments.

    Returns a PlanPrediction: displacements ``(increments + 1, n, 3)`` mm, each increment's
    element quality, ``prescribed`` each increment's bone motion (moving nodes)."""

    t0 = time.perf_counter()
    data = DatabaseConfig(**model.bundle.data["database"])
    response, U, bones = _baseline_trajectory(model, residual, face, plan, segments)
    mesh = face_mesh_and_segments(face, segments)[0]
    U = with_exact_attachment(U, mesh.points, response.bc, plan)
    quality = [mesh.with_points(mesh.points + u).scaled_jacobian() for u in U[1:]]
    wall = time.perf_counter() - t0
    reports = [IncrementReport(k, wall / len(quality), 0.0, 0, 0, 0, float(q.min()), int(np.argmin(q)),
                               0.0, 0.0, 0.0, 0) for k, q in enumerate(quality, start=1)]
    prescribed = np.where((response.bc.types == 1)[None, :, None], bones, 0.0)
    return with_answer_checks(
        PlanPrediction(mesh, U, response.bc, reports, wall, "baseline (sliding response + POD residual)",
                       data.sliding, extrapolation=model.extrapolation(plan, mesh), prescribed=prescribed), plan)


def _scale_field(calibration_scale: str, network: np.ndarray | None, baseline: np.ndarray) -> np.ndarray:
    """Per-node scale ``(n,)`` mm from the network's and the baseline's final displacements
    ``(n, 3)`` mm (see the module)."""
    if calibration_scale == "constant":
        return np.ones(baseline.shape[0])
    return np.linalg.norm(network - baseline, axis=1) + SCALE_FLOOR_MM


def _case_scale(node_scale: np.ndarray) -> float:
    return float(np.percentile(node_scale, 95))


def calibrate_surrogate(model, database, *, coverage: float = 0.9, scale: str = "auto", keys=None,
                        training=None, answerer: str = "auto", progress: bool = True) -> Calibration:
    """Calibrate ``model``'s error estimate on whole simulations of ``database`` it has not seen.

    Parameters
    ----------
    model : :class:`~toolkit.static.surrogate.Surrogate`
    database : path of a static database or a StaticDatabase: the model's training database
        (its test simulations are used) or another one of the same settings (every simulation
        the model did not train or validate on)
    coverage : probability the bound holds for a new plan like these (at least
        :func:`~toolkit.common.training.conformal.min_calibration_cases` plans are needed)
    scale : one of :data:`SCALES`, or ``auto`` (default): with ``answerer="auto"``, the cheapest
        scale and answerer whose bound, averaged over the calibration plans, is within
        :data:`AUTO_BOUND_SLACK` of the narrowest (see the module)
    keys : calibrate on these simulations instead
    training : the database the model was trained on (default ``database``): the baseline's
        residual regression, the training plans and subjects come from its simulations the model
        trained or validated on
    answerer : one of :data:`ANSWERERS` (see the module)
    progress : tqdm over the plans

    Returns
    -------
    Calibration (not saved: ``.save(model_directory)``)
    """
    from tqdm import tqdm


    if scale not in SCALES + ("auto",):
        raise ValueError(f"scale = {scale!r}; expected one of {SCALES + ('auto',)}")
    if answerer not in ANSWERERS:
        raise ValueError(f"answerer = {answerer!r}; expected one of {ANSWERERS}")
    db = database if isinstance(database, StaticDatabase) else StaticDatabase.open(database)
    keys, how = evaluation_keys(model, db, keys)
    train_db = db if training is None else (training if isinstance(training, StaticDatabase)
                                            else StaticDatabase.open(training))
    if train_db is not db:
        check_database(model, train_db)
    identities = _simulation_identities(train_db)
    seen = set(model.bundle.extra.get("seen_simulations") or [])
    seen_keys = [k for k in train_db.samples.key.unique() if identities[str(k)] in seen]
    if not seen_keys:
        raise ValueError(f"{train_db.path} holds none of the simulations the model trained on: give its training "
                         "database too (training=...; command line: --train-data DB.h5)")
    need = min_calibration_cases(coverage)
    if len(keys) < need:
        raise ValueError(f"{len(keys)} held-out simulation(s) in {db.path} ({how}); a bound at {coverage:.0%} "
                         f"needs at least {need}: generate more plans (`toolkit static database --plans`) or lower "
                         "--coverage")
    # the baseline: each seen simulation's sliding response, and the regression of what it misses
    rows = np.flatnonzero(train_db.samples.key.isin(seen_keys).to_numpy())
    seen_data = train_db.arrays(rows)
    responses = {}
    for sid in np.unique(seen_data["subject"]):
        subject = train_db.subject(int(sid))
        responses[int(sid)] = model.sliding_response(_face(subject), subject.segments)
    linear = np.stack([responses[int(sid)].increment(b, x)
                       for sid, b, x in zip(seen_data["subject"], seen_data["bone"], seen_data["x"])])
    params = train_db.samples[list(PLAN_FEATURES)].to_numpy(np.float64)[rows]
    residual = LinearPlusPOD.fit(params, seen_data["v"], linear)
    last = train_db.samples[train_db.samples.key.isin(seen_keys)].sort_values("increment").groupby("key").tail(1)
    train_plans = last[list(PLAN_FEATURES[:len(PLAN_PARAMETERS)])].to_numpy(np.float64)
    plan_ranges = {n: [float(train_plans[:, j].min()), float(train_plans[:, j].max())]
                   for j, n in enumerate(PLAN_PARAMETERS)}
    seen_subjects = sorted({int(s) for s in train_db.samples.subject[train_db.samples.key.isin(seen_keys)]})
    pts = np.stack([train_db.points[s] for s in seen_subjects])
    hull = training_hull(train_db.config.to_dict())
    stored = model.bundle.extra.get("arch_nodes")  # the model's own, so that predict gives the same verdict
    arch = np.asarray(stored, np.int64) if stored is not None else surrogate_arch_nodes(train_db)
    spread = max([_rms(a, b) for i, a in enumerate(pts) for b in pts[i + 1:]] + [MIN_SHAPE_SPREAD_MM])
    cases = []
    fe_s = db.samples.groupby("key").seconds.sum()
    for key in tqdm(keys, desc="calibration plans", disable=not progress):
        sid = int(db.samples.subject[db.samples.key == key].iloc[0])
        subject, plan = db.subject(sid), db.plan(key)
        t0 = time.perf_counter()
        pred = model.predict_plan(_face(subject), plan, segments=subject.segments)
        t1 = time.perf_counter()
        base = _baseline_trajectory(model, residual, _face(subject), plan, subject.segments)[1][-1]
        t2 = time.perf_counter()
        fe = db.displacements(key)[-1]
        cases.append({"key": str(key), "subject": sid, "error_mm": answer_error(pred.displacement, fe),
                      "baseline_error_mm": answer_error(base, fe),
                      "disagreement_mm": _case_scale(_scale_field("disagreement", pred.displacement, base)),
                      "network_s": t1 - t0, "baseline_s": t2 - t1, "fe_s": float(fe_s[key])})
    scale, answerer, bounds, candidates = _choose(cases, coverage, scale, answerer)
    for c in cases:
        c["scale_mm"] = 1.0 if scale == "constant" else c["disagreement_mm"]
    return Calibration(scale, bounds[answerer], residual, train_plans, plan_ranges, pts, float(spread),
                       db.config.material, cases, {"database": str(Path(db.path).resolve()), "plans": how,
                                                   "training_database": str(Path(train_db.path).resolve())},
                       answerer, bounds, hull, arch, candidates)


def _choose(cases: list, coverage: float, scale: str, answerer: str) -> tuple[str, str, dict, tuple]:
    """The scale and answerer a calibration keeps (see the module), the bounds by answerer with
    that scale, and the candidate pairs asked for: among them, the cheapest (median seconds per
    calibration plan) whose mean bound is within :data:`AUTO_BOUND_SLACK` of the narrowest."""
    candidates = tuple((s, a) for s in (SCALES if scale == "auto" else (scale,))
                       for a in (("network", "baseline") if answerer == "auto" else (answerer,)))
    mean = {c: _mean_bound(cases, *c, coverage) for c in candidates}
    near = [c for c in candidates if mean[c] <= AUTO_BOUND_SLACK * min(mean.values())]
    cost = {c: float(np.median([_pair_seconds(case, *c) for case in cases])) for c in near}
    scale, answerer = min(near, key=lambda c: (cost[c], mean[c]))
    return scale, answerer, _bounds(cases, _case_scales(cases, scale), coverage), candidates


def _case_scales(cases: list, scale: str) -> np.ndarray:
    """Each calibration plan's scale (mm) under ``scale``."""
    return np.array([1.0 if scale == "constant" else c["disagreement_mm"] for c in cases])


def _bounds(cases: list, scales: np.ndarray, coverage: float) -> dict:
    """answerer -> the ConformalBound of its errors over ``scales``."""
    return {"network": calibrate([c["error_mm"] for c in cases], scales, coverage),
            "baseline": calibrate([c["baseline_error_mm"] for c in cases], scales, coverage)}


def _mean_bound(cases: list, scale: str, answerer: str, coverage: float) -> float:
    scales = _case_scales(cases, scale)
    return float(np.mean(_bounds(cases, scales, coverage)[answerer].bound(scales)))


def _pair_seconds(case: dict, scale: str, answerer: str) -> float:
    """Seconds of an answer on a calibration plan: the answerer, and both models for the disagreement scale."""
    return case["network_s"] + case["baseline_s"] if scale == "disagreement" else case[f"{answerer}_s"]


def _face(subject):
    """What predict_plan and simulate take for a database subject: the phantom, or the mesh."""

    return subject if isinstance(subject, FacePhantom) else subject.mesh


def _rms(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=1))))


def estimate(calibration: Calibration, network=None, baseline=None) -> dict:
    """The calibrated error estimate of an answer.

    Parameters
    ----------
    calibration : Calibration
    network, baseline : the network's PlanPrediction (:meth:`~toolkit.static.surrogate.Surrogate.predict_plan`)
        and the baseline's (:func:`baseline_prediction`) of the same plan: the disagreement scale
        needs both, the constant scale only the answerer's

    Returns ``{"bound_mm", "coverage", "scale", "scale_mm", "node_mm", "answerer"}``: ``bound_mm``
    bounds the error of the ``answerer``'s answer (95th percentile of the nodal error) with
    probability ``coverage`` for a plan like the calibration ones; ``node_mm`` ``(n,)`` is the
    per-node estimate (the factor times each node's scale; its 95th percentile is ``bound_mm``).
    """
    given = network if calibration.answerer == "network" else baseline
    if given is None or (calibration.scale == "disagreement" and (network is None or baseline is None)):
        need = "both predictions" if calibration.scale == "disagreement" else f"the {calibration.answerer}'s prediction"
        raise ValueError(f"the {calibration.scale} scale of this calibration needs {need}")
    node = _scale_field(calibration.scale, None if network is None else network.displacement,
                        given.displacement if baseline is None else baseline.displacement)
    return {"bound_mm": float(calibration.bound.bound(_case_scale(node))), "coverage": calibration.bound.coverage,
            "scale": calibration.scale, "scale_mm": _case_scale(node), "node_mm": calibration.bound.bound(node),
            "answerer": calibration.answerer}


def out_of_distribution(calibration: Calibration, mesh, plan, material: str | None = None,
                        same_topology: bool = True) -> dict:
    """Whether the inputs lie beyond what the model learned.

    Returns ``{"outside": bool, "reasons": [str], "plan": extrapolation dict with
    ``nearest_plan_distance`` (the distance to the nearest training plan, each parameter over
    its training span), "shape": {"rms_to_nearest_subject_mm", "training_spread_mm",
    "outside_envelope_mm"}, "material": {"asked", "trained"}}``.

    A plan is outside when it lies beyond what the training database's sampler spans: one of
    its :func:`~toolkit.static.plan.sampled_parameters` (translation lengths and rotation
    angles, out-of-plane motion for a sagittal database, and the jaw closing on a face of the
    training topology) lies outside :attr:`Calibration.plan_hull`. The calibration's plans
    are drawn like the training ones, so the bound's coverage holds up to the edges of the
    ranges; the box of the training plans' own parameters is narrower (a translation drawn
    uniform in length and direction has components thin near their extremes, and 80 plans
    leave corners of the ranges outside their box).

    The face is another shape when it lies farther (RMS) from every training subject than they
    lie from each other, or when one of its nodes lies more than :data:`MIN_SHAPE_SPREAD_MM`
    outside the per-coordinate box of that node over the training subjects.
    """

    reasons = []
    same_shape = same_topology and mesh.points.shape == calibration.subjects.shape[1:]
    arch = mesh.points[calibration.arch_nodes] if same_shape and "jaw_closing_mm" in calibration.plan_hull \
        else None
    ex = plan_extrapolation(plan, calibration.plan_hull, arch)
    values = np.array(_plan_values(plan))
    lo = np.array([calibration.plan_ranges[n][0] for n in PLAN_PARAMETERS])
    span = np.array([calibration.plan_ranges[n][1] for n in PLAN_PARAMETERS]) - lo
    span[span <= 0] = 1.0
    ex["nearest_plan_distance"] = float(np.min(np.linalg.norm((calibration.train_plans - values) / span, axis=1)))
    if ex["outside"]:
        reasons.append("plan: " + describe_extrapolation(ex))
    shape: dict[str, float | None] = {"training_spread_mm": calibration.shape_spread_mm}
    if not same_shape:
        shape.update(rms_to_nearest_subject_mm=None, outside_envelope_mm=None)
        reasons.append("face: a mesh of another topology than the training subjects")
    else:
        d = min(_rms(mesh.points, s) for s in calibration.subjects)
        lo, hi = calibration.subjects.min(axis=0), calibration.subjects.max(axis=0)
        beyond = float(np.linalg.norm(np.maximum(lo - mesh.points, 0) + np.maximum(mesh.points - hi, 0),
                                      axis=1).max())
        shape.update(rms_to_nearest_subject_mm=d, outside_envelope_mm=beyond)
        if d > calibration.shape_spread_mm:
            reasons.append(f"face: {d:.2f} mm (RMS over nodes) from the nearest training subject, farther than the "
                           f"training subjects lie from each other ({calibration.shape_spread_mm:.2f} mm)")
        elif beyond > MIN_SHAPE_SPREAD_MM:
            reasons.append(f"face: a node lies {beyond:.2f} mm outside the box its training subjects span")
    mat = {"asked": material or calibration.material, "trained": calibration.material}
    if mat["asked"] != mat["trained"]:
        reasons.append(f"material: {mat['asked']}, the model was trained on {mat['trained']}")
    return {"outside": bool(reasons), "reasons": reasons, "plan": ex, "shape": shape, "material": mat}


def _plan_values(plan) -> list[float]:

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return plan_features(plan, 1)[0][:len(PLAN_PARAMETERS)].tolist()


@dataclass(frozen=True, eq=False)
class TrustedAnswer:
    """An answer within a tolerance: the surrogate's prediction or the FE's result.

    result : PlanPrediction (``answered_by == "surrogate"``) or SimulationResult (``"fe"``)
    answered_by : ``surrogate`` (the network), ``baseline`` (the sliding response + POD residual baseline,
        when the calibration chose it) or ``fe``
    reason : why (one line)
    tolerance_mm : the tolerance asked
    estimate : :func:`estimate` of the answer (``node_mm`` left out of the summary)
    ood : :func:`out_of_distribution`
    seconds : ``surrogate``, ``estimate``, ``fe`` (0 when not run), ``total``
    """

    result: SimulationResult
    answered_by: str
    reason: str
    tolerance_mm: float
    estimate: dict
    ood: dict
    seconds: dict

    def summary(self) -> dict:
        est = {k: v for k, v in self.estimate.items() if k != "node_mm"}
        return {**self.result.summary(), "answer": {
            "answered_by": self.answered_by, "reason": self.reason, "tolerance_mm": self.tolerance_mm,
            "estimate": est, "out_of_distribution": self.ood, "seconds": self.seconds}}

    def write(self, out, preview: bool = True) -> Path:
        """The result's files (``toolkit static simulate``'s), ``summary.json`` with ``answer``,
        and ``error_estimate`` (mm, per node) in ``result.vtu`` when the surrogate answered."""

        fields = {"error_estimate": self.estimate["node_mm"]} if self.answered_by != "fe" else {}
        out = self.result.write(out, preview=preview, point_data=fields)
        with atomic_path(out / "summary.json") as tmp:
            tmp.write_text(json.dumps(jsonable(self.summary()), indent=2))
        return out


def answer(model, face, plan, tolerance_mm: float, *, segments=None, calibration: Calibration | None = None,
           coverage: float | None = None, material: str | None = None, any_mesh: bool = False,
           options=None) -> TrustedAnswer:
    """The calibrated answer (the network's or the sliding response + POD residual baseline's, with
    the scale and answerer :meth:`Calibration.for_tolerance` takes for ``tolerance_mm``) when its
    estimate is within ``tolerance_mm`` and the inputs are like the training data; otherwise the
    FE of the same plan.

    Parameters
    ----------
    model : Surrogate (its directory must hold a calibration, or pass ``calibration``)
    face, plan, segments : as for :meth:`~toolkit.static.surrogate.Surrogate.predict_plan`
    any_mesh : accepted like ``predict_plan``'s; a mesh of another topology than the training
        meshes has no error estimate (the baseline's residual is node-indexed), so the FE answers
    tolerance_mm : mm, > 0: the largest answer error (95th percentile of the nodal error) accepted
    calibration : default :meth:`Calibration.load` of the model's directory
    coverage : the estimate's coverage (default the calibration's)
    material : the tissue material asked (default the training database's); another one is
        out of distribution, so the FE answers with it
    options : SimulationOptions for the FE (default its defaults, release-band retries included)
    """

    tolerance_mm = check_tolerance(tolerance_mm, 0.5)
    calibration = calibration or Calibration.load(model.directory)
    if coverage is not None:
        calibration = calibration.at(coverage)
    calibration = calibration.for_tolerance(tolerance_mm)
    data = DatabaseConfig(**model.bundle.data["database"])
    mesh, segments = face_mesh_and_segments(face, segments)
    same = _same_topology(model, mesh)
    ood = out_of_distribution(calibration, mesh, plan, material, same_topology=same)
    t0 = time.perf_counter()
    est, given = {}, None
    seconds = {"surrogate": 0.0, "estimate": 0.0, "fe": 0.0}
    if same:  # the baseline's residual is node-indexed: the training topology only
        network = base = None
        if calibration.answerer == "network" or calibration.scale == "disagreement":
            network = model.predict_plan(face, plan, segments=segments)
        if calibration.answerer == "baseline" or calibration.scale == "disagreement":
            base = baseline_prediction(model, calibration.residual, face, plan, segments)
        given = network if calibration.answerer == "network" else base
        seconds["surrogate"] = time.perf_counter() - t0
        t1 = time.perf_counter()
        est = estimate(calibration, network, base)
        seconds["estimate"] = time.perf_counter() - t1

    def checks():  # called only with an estimate, made with the answer
        assert given is not None
        return given.checks["answer"]

    decision = decide(tolerance_mm, ood, est, checks, no_estimate="no error estimate for this face")
    if decision.surrogate:
        assert given is not None  # an answer given has been predicted
        who = "surrogate" if calibration.answerer == "network" else "baseline"
        seconds["total"] = time.perf_counter() - t0
        return TrustedAnswer(given, who, decision.reason, tolerance_mm, est, ood, seconds)
    reason = decision.reason
    t1 = time.perf_counter()
    fe = simulate(face, plan, data.increments, material or data.material, data.sliding, segments=segments,
                  **({"options": options} if options is not None else {}))
    seconds["fe"] = time.perf_counter() - t1
    seconds["total"] = time.perf_counter() - t0
    return TrustedAnswer(fe, "fe", reason, float(tolerance_mm), est, ood, seconds)


def _same_topology(model, mesh) -> bool:

    return model.bundle.data.get("mesh") == mesh_fingerprint(mesh.points, dict(mesh.cells))
