"""Static surrogate answers within a tolerance: the calibrated error estimates and the FE fallback
(:mod:`toolkit.static.trust`) on in-distribution and out-of-distribution cases, against the FE of
each case.

Stages (each resumable: rerun the same command to continue):

1. the paper-size database and default PointNet++ of ``surrogate_remeshed.py`` (``--subjects``
   paper phantom subjects x ``--plans`` sagittal plans, ``--max-minutes`` of training), shared
   with it in ``benchmarks/work/``;
2. calibration of each scale (``disagreement``, ``constant``) on the model's test plans, and of a
   deep ensemble measured beside them (``--ensemble`` members: the model and more trained like it
   with other seeds on its split; answer: the members' mean; scale: their spread, the root mean
   square distance of the members to the mean, 95th percentile over nodes);
3. cases, the FE of each cached in ``work/trust_fe/`` (with the time of the run that computed it):

   - ``in``: ``--cases`` sampled plans (the physiological ranges) on the training subjects, drawn
     with another seed than the database's;
   - ``plan 1.2-2x``: plans whose translations lie between 1.2 and 2 times the top of the
     physiological range (rotations within it);
   - ``shape``: an unseen subject whose face width, height and tissue thickness lie beyond those
     of every training subject (at the end of the phantom's validated range farthest from them);
   - ``neo-hookean``: in-range plans on subject 0 whose FE uses the Neo-Hookean material (the
     model was trained on the linear one);

4. per case and scale: the answer error (95th percentile over all nodes of the network's nodal
   error against the FE), the bound at 90 % and 95 %, the out-of-distribution check, the time of
   the network, the baseline, the estimate and the FE, for the network's answer and for the
   sliding response + POD residual baseline's (the two answerers a calibration can choose); for
   the Neo-Hookean cases, the FE again started from the baseline's answer
   (``simulate(initial_guess=)``): its time, Newton iterations and largest difference to the
   cold run; and the policy of
   ``toolkit static predict --tolerance`` at each of ``--tolerances`` mm (the baseline with the
   constant scale is timed without the network, as ``answer`` runs it): the share of delivered
   answers within it, the share of in-distribution cases the surrogate answers, and the mean time
   per answer against always running the FE, with the pair ``predict --tolerance`` takes there
   under the default calibration (``default``).

Writes ``benchmarks/results/surrogate_trust_static.csv`` (one row per case, scale and answerer), the
summary in its sidecar's ``extra``, and ``docs/figures/surrogate_trust_static.png`` (estimated
bound against true error).

With ``--workflow impact``, the same for the impact LSTM (``surrogate_trust_impact.py``).

    python benchmarks/surrogate_trust.py --cases 40           # 4 x 25 plans, 3 x 8 min, 40 + 40 + 20 + 20 cases
    python benchmarks/surrogate_trust.py --subjects 2 --plans 25 --max-minutes 0.3 --cases 4 --suffix _smoke
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, WORK, write_result
from surrogate_remeshed import add_training_arguments, stage_database, stage_model

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/", "toolkit/impact/", "toolkit/common/training/", "toolkit/common/fem/",
            "toolkit/common/meshes/", "toolkit/common/phantoms/", "toolkit/common/analysis/",
            "toolkit/common/papers.py")

FIGURES = Path(__file__).resolve().parent.parent / "docs" / "figures"
COVERAGES = (0.9, 0.95)
#: whose answer each row bounds: PointNet++ or the sliding response + POD residual baseline
ANSWERED_BY = ("network", "baseline")
#: mm: the AUROC of each estimate for flagging answers whose error exceeds these
AUROC_AT_MM = (0.5, 1.0, 2.0, 4.0)


def stage_members(args, db_path: Path, model) -> list:
    """The deep ensemble: ``model`` and ``--ensemble - 1`` more trained like it with seeds
    ``seed + k`` on its split (``split_seed``), so that every member holds out the same test plans
    (``work/remeshed_model_member<k>``)."""
    from dataclasses import replace

    from toolkit.static.surrogate import Surrogate, train_surrogate

    split = model.config.seed if model.config.split_seed is None else model.config.split_seed
    members = [model]
    for k in range(1, args.ensemble):
        out = WORK / f"remeshed_model{args.suffix}_member{k}"
        if (out / "model.pt").exists():
            member = Surrogate.load(out)
        else:
            member = train_surrogate(db_path, replace(model.config, seed=model.config.seed + k, split_seed=split),
                                     out=out, resume=(out / "checkpoint.pt").exists())
        if sorted(member.bundle.extra["test_keys"]) != sorted(model.bundle.extra["test_keys"]):
            raise RuntimeError(f"{out} holds out other test plans than the model: delete it and rerun")
        members.append(member)
    return members


def ensemble_prediction(members, face, plan) -> tuple[np.ndarray, np.ndarray, float]:
    """The members' mean final displacement ``(n, 3)`` mm, each node's spread (root mean square
    distance of the members to the mean, mm) and the time of all members (s)."""
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        u = np.stack([m.predict_plan(face, plan).displacement for m in members])
    mean = u.mean(axis=0)
    return mean, np.sqrt(np.mean(np.sum((u - mean) ** 2, axis=2), axis=0)), time.perf_counter() - t0


def auroc(flag: np.ndarray, score: np.ndarray) -> float:
    """Area under the ROC curve of ``score`` for ``flag`` (Mann-Whitney, ties averaged); nan
    when one class is empty."""
    from scipy.stats import rankdata

    flag = np.asarray(flag, bool)
    n1, n0 = int(flag.sum()), int((~flag).sum())
    if not n1 or not n0:
        return float("nan")
    r = rankdata(score)
    return float((r[flag].sum() - n1 * (n1 + 1) / 2) / (n1 * n0))


def extreme_shape(subjects: list[int]):
    """A FaceShape beyond every training subject in width, height and tissue thickness."""
    from toolkit.common.phantoms.phantom import FaceShape

    shapes = [FaceShape() if s == 0 else FaceShape.sample(s) for s in subjects]
    values = {}
    for name in ("face_width", "face_height", "tissue_thickness"):
        lo, hi = FaceShape.RANGES[name]
        seen = [getattr(s, name) for s in shapes]
        values[name] = lo if min(seen) - lo > hi - max(seen) else hi
    return FaceShape(**values)


def beyond_ranges(factor_lo: float, factor_hi: float):
    """Ranges whose translations lie between ``factor_lo`` and ``factor_hi`` times the top of the
    physiological range, rotations within it."""
    from toolkit.static.plan import PHYSIOLOGICAL_RANGES, MotionRange

    return {k: MotionRange((factor_lo * r.translation_mm[1], factor_hi * r.translation_mm[1]), r.rotation_deg)
            for k, r in PHYSIOLOGICAL_RANGES.items()}


def make_cases(args, subjects: list[int]) -> list[dict]:
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.static.database import subject_phantom
    from toolkit.static.plan import PHYSIOLOGICAL_RANGES, sample_plans

    cases = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        per_subject = -(-args.cases // len(subjects))
        draws = (("in", 1000, PHYSIOLOGICAL_RANGES), ("plan 1.2-2x", 2000, beyond_ranges(1.2, 2.0)))
        for kind, stream, ranges in draws:
            drawn = {s: sample_plans(per_subject, np.random.default_rng([args.seed, stream + s]), "sagittal", ranges,
                                     phantom=subject_phantom("paper", s)) for s in subjects}
            for i in range(args.cases):
                s = subjects[i % len(subjects)]
                cases.append({"kind": kind, "subject": s, "shape": None, "plan": drawn[s][i // len(subjects)],
                              "material": "linear"})
        shape = extreme_shape(subjects)
        phantom = face_hex("paper", shape)
        for plan in sample_plans(max(args.cases // 2, 1), np.random.default_rng([args.seed, 3000]), "sagittal",
                                 phantom=phantom):
            cases.append({"kind": "shape", "subject": None, "shape": shape, "plan": plan, "material": "linear"})
        for plan in sample_plans(max(args.cases // 2, 1), np.random.default_rng([args.seed, 4000]), "sagittal",
                                 phantom=subject_phantom("paper", 0)):
            cases.append({"kind": "neo-hookean", "subject": 0, "shape": None, "plan": plan,
                          "material": "neo-hookean"})
    return cases


def case_face(case):
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.static.database import subject_phantom

    return face_hex("paper", case["shape"]) if case["shape"] is not None else subject_phantom("paper", case["subject"])


def fe_of(case, face, data: dict, cache: Path, guess: np.ndarray | None = None
          ) -> tuple[np.ndarray | None, float, str, float]:
    """The FE's final displacement (cached), its time, status and Newton iterations (nan when the
    cached run did not record them; a Neo-Hookean case's run is then redone); ``guess``: the FE
    started from that answer (``simulate(initial_guess=)``), cached apart."""
    from toolkit.static.simulate import simulate

    tag = hashlib.sha1(json.dumps([case["plan"].to_dict(), case["material"], case["subject"],
                                   None if case["shape"] is None else str(case["shape"]), data["increments"],
                                   data["sliding"]] + ([] if guess is None else ["warm"]),
                                  sort_keys=True, default=str).encode()).hexdigest()[:16]
    file = cache / f"{tag}.npz"
    if file.exists():
        z = np.load(file)
        if "newton" in z or case["material"] == "linear":
            return ((z["u"] if z["u"].size else None), float(z["seconds"]), str(z["status"]),
                    float(z["newton"]) if "newton" in z else np.nan)
    t0 = time.perf_counter()
    newton = np.nan
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            result = simulate(face, case["plan"], data["increments"], case["material"], data["sliding"],
                              initial_guess=guess)
        u, status, newton = result.displacement, "ok", float(sum(r.newton_iterations for r in result.reports))
    except Exception as exc:  # noqa: BLE001 - recorded
        u, status = None, f"{type(exc).__name__}: {str(exc)[:160]}"
    seconds = time.perf_counter() - t0
    np.savez(file, u=np.zeros(0) if u is None else u, seconds=seconds, status=status, newton=newton)
    return u, seconds, status, newton


def _bound_at(bound, coverage: float, scale_mm: float) -> float:
    try:
        return float(bound.at(coverage).bound(scale_mm))
    except ValueError:  # too few calibration plans for this coverage
        return np.nan


def _rows(df: pd.DataFrame, scale: str, answerer: str | None) -> pd.DataFrame:
    d = df[(df.scale == scale) & (df.fe_status == "ok")]
    return d if answerer is None or "answerer" not in d else d[d.answerer == answerer]


def policy(df: pd.DataFrame, scale: str, coverage: float, tolerance: float, answerer: str | None = None) -> dict:
    """What ``predict --tolerance`` does over the cases with one scale, coverage and answerer."""
    d = _rows(df, scale, answerer)
    bound = d[f"bound_{int(coverage * 100)}_mm"]
    by_surrogate = ~d.ood & (bound <= tolerance)
    delivered_error = np.where(by_surrogate, d.error_mm, 0.0)  # the FE's answer is the reference itself
    seconds = d.surrogate_s + d.estimate_s + np.where(by_surrogate, 0.0, d.fe_s)
    inside = d.kind == "in"
    return {"scale": scale, "answerer": answerer, "coverage": coverage, "tolerance_mm": tolerance,
            "cases": int(len(d)), "answered_by_surrogate": float(by_surrogate.mean()),
            "in_distribution_answered_by_surrogate": float(by_surrogate[inside].mean()) if inside.any() else None,
            "delivered_within_tolerance": float(np.mean(delivered_error <= tolerance)),
            "mean_answer_s": float(seconds.mean()), "mean_fe_s": float(d.fe_s.mean()),
            "speedup_vs_fe": float(d.fe_s.mean() / seconds.mean()),
            "in_distribution_speedup_vs_fe": (float(d.fe_s[inside].mean() / seconds[inside].mean())
                                              if inside.any() else None)}


def method_scores(df: pd.DataFrame, scale: str, answerer: str | None = None) -> dict:
    d = _rows(df, scale, answerer)
    out = {"scale": scale, "answerer": answerer, "estimate_s": float(d.estimate_s.mean())}
    for at in AUROC_AT_MM:
        out[f"auroc_{at:g}mm"] = auroc(d.error_mm > at, d.scale_mm) if scale != "constant" else 0.5
    for c in COVERAGES:
        b = d[f"bound_{int(c * 100)}_mm"]
        for name, part in (("in", d.kind == "in"), ("out", d.kind != "in")):
            out[f"coverage_{int(c * 100)}_{name}"] = float((d.error_mm[part] <= b[part]).mean()) if part.any() else None
        out[f"width_{int(c * 100)}_in_mm"] = float(b[d.kind == "in"].mean())
    return out


def plot(df: pd.DataFrame, tolerance: float, out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = df[(df.scale == "disagreement") & (df.fe_status == "ok")]
    fig, axes = plt.subplots(1, 2, figsize=(9.6, 4.4), dpi=120)
    for ax, answerer, name in zip(axes, ANSWERED_BY, ("PointNet++", "sliding response + POD residual")):
        a = d[d.answerer == answerer]
        for kind, marker in (("in", "o"), ("plan 1.2-2x", "^"), ("shape", "s"), ("neo-hookean", "D")):
            k = a[a.kind == kind]
            ax.scatter(k.bound_90_mm, k.error_mm, marker=marker, s=22, label=kind, alpha=0.8)
        top = float(max(a.bound_90_mm.max(), a.error_mm.max()) * 1.05)
        ax.plot([0, top], [0, top], "k-", lw=0.8, label="error = bound")
        ax.axhline(tolerance, color="grey", ls="--", lw=0.8)
        ax.axvline(tolerance, color="grey", ls="--", lw=0.8)
        ax.set(xlabel="estimated bound at 90 % (mm)", ylabel="true answer error, p95 over nodes (mm)",
               title=f"{name} answers (disagreement scale)", xlim=(0, top), ylim=(0, top))
        ax.legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)


def main(argv=None):
    import surrogate_trust_impact

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--workflow", choices=["static", "impact"], default="static",
                    help="static: PointNet++ (this module); impact: the LSTM (surrogate_trust_impact.py)")
    add_training_arguments(ap)
    surrogate_trust_impact.add_arguments(ap)
    ap.add_argument("--cases", type=int, default=20, help="in-distribution and beyond-range cases (half as many "
                                                          "for the unseen shape and for Neo-Hookean)")
    ap.add_argument("--ensemble", type=int, default=3,
                    help="members of the deep ensemble measured beside the calibrated scales (the default model and "
                         "ENSEMBLE - 1 more trained with other seeds on its split; 1: none)")
    ap.add_argument("--tolerances", type=float, nargs="+", default=None,
                    help="mm: the policy of predict --tolerance at each (default static 0.5 1 2 4, impact "
                         "0.02 0.05 0.5 1)")
    ap.add_argument("--out", type=Path, default=None,
                    help="default benchmarks/results/surrogate_trust_WORKFLOW.csv")
    args = ap.parse_args(argv)
    args.out = args.out or RESULTS / f"surrogate_trust_{args.workflow}.csv"
    if args.workflow == "impact":
        args.tolerances = args.tolerances or [0.02, 0.05, 0.5, 1.0]
        return surrogate_trust_impact.main(args, argv)
    args.tolerances = args.tolerances or [0.5, 1.0, 2.0, 4.0]

    from tqdm import tqdm

    from toolkit.common.runtime import set_threads
    from toolkit.common.training.conformal import calibrate, min_calibration_cases
    from toolkit.static.database import StaticDatabase
    from toolkit.static.trust import (
        SCALE_FLOOR_MM,
        SCALES,
        _case_scale,
        answer_error,
        baseline_prediction,
        calibrate_surrogate,
        estimate,
        out_of_distribution,
    )

    set_threads(1)
    db_path = stage_database(args)
    model = stage_model(args, db_path)
    data = model.bundle.data["database"]
    calibrations = {}
    for scale in SCALES:
        t0 = time.perf_counter()
        calibrations[scale] = calibrate_surrogate(model, db_path, coverage=COVERAGES[0], scale=scale)
        print(f"calibration {scale}: {calibrations[scale].bound.n} plans, factor {calibrations[scale].bound.factor:.3g}"
              f" ({time.perf_counter() - t0:.0f} s)", flush=True)
    auto = calibrate_surrogate(model, db_path, coverage=COVERAGES[0])  # the defaults: scale and answerer "auto"
    print(f"calibration auto: {auto.scale} scale, answers by the {auto.answerer}", flush=True)
    members = stage_members(args, db_path, model) if args.ensemble > 1 else []
    ensemble_bound = None
    if members:  # the deep ensemble's spread, calibrated on the same held-out plans
        db = StaticDatabase.open(db_path)
        errors, scales = [], []
        for c in calibrations["constant"].cases:
            mean, spread, _ = ensemble_prediction(members, db.subject(c["subject"]), db.plan(c["key"]))
            errors.append(answer_error(mean, db.displacements(c["key"])[-1]))
            scales.append(_case_scale(spread + SCALE_FLOOR_MM))
        ensemble_bound = calibrate(errors, scales, COVERAGES[0])
        print(f"calibration ensemble ({len(members)} members): factor {ensemble_bound.factor:.3g}", flush=True)
    cache = WORK / f"trust_fe{args.suffix}"
    cache.mkdir(parents=True, exist_ok=True)
    rows = []
    for i, case in enumerate(tqdm(make_cases(args, list(range(args.subjects))), desc="cases")):
        face = case_face(case)
        fe, fe_s, status, fe_newton = fe_of(case, face, data, cache)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            t0 = time.perf_counter()
            pred = model.predict_plan(face, case["plan"])
            network_s = time.perf_counter() - t0
            t0 = time.perf_counter()  # the face's sliding response is built at its first plan, then cached
            base_pred = baseline_prediction(model, calibrations["constant"].residual, face, case["plan"])
            baseline_s = time.perf_counter() - t0
        base = {"case": i, "kind": case["kind"], "subject": case["subject"], "material": case["material"],
                "fe_status": status, "fe_s": fe_s, "fe_newton": fe_newton, "network_s": network_s,
                "baseline_s": baseline_s}
        if case["material"] != data["material"] and fe is not None:  # Newton: the FE warm-started from the baseline
            warm, warm_s, warm_status, warm_newton = fe_of(case, face, data, cache, guess=base_pred.displacements)
            base.update(fe_warm_s=warm_s, fe_warm_newton=warm_newton, fe_warm_status=warm_status,
                        fe_warm_max_diff_mm=float(np.abs(warm - fe).max()) if warm is not None else np.nan)
        for scale, cal in calibrations.items():
            ood = out_of_distribution(cal, face.mesh, case["plan"], case["material"])
            for answerer in ANSWERED_BY:
                t0 = time.perf_counter()
                est = estimate(replace(cal, answerer=answerer, bound=cal.bounds[answerer]), pred, base_pred)
                estimate_s = time.perf_counter() - t0
                given = pred if answerer == "network" else base_pred
                # what answer() runs: the answerer, and the other one too for the disagreement scale
                surrogate_s = network_s + baseline_s if scale == "disagreement" else \
                    {"network": network_s, "baseline": baseline_s}[answerer]
                row = {**base, "scale": scale, "answerer": answerer, "surrogate_s": surrogate_s,
                       "estimate_s": estimate_s, "scale_mm": est["scale_mm"],
                       "error_mm": answer_error(given.displacement, fe) if fe is not None else np.nan,
                       "ood": ood["outside"], "ood_reasons": " | ".join(ood["reasons"]),
                       "nearest_plan_distance": ood["plan"]["nearest_plan_distance"],
                       "shape_rms_mm": ood["shape"]["rms_to_nearest_subject_mm"],
                       "shape_outside_envelope_mm": ood["shape"]["outside_envelope_mm"]}
                for c in COVERAGES:
                    row[f"bound_{int(c * 100)}_mm"] = _bound_at(cal.bounds[answerer], c, est["scale_mm"])
                rows.append(row)
        if ensemble_bound is not None:
            mean, spread, ensemble_s = ensemble_prediction(members, face, case["plan"])
            ood = out_of_distribution(calibrations["constant"], face.mesh, case["plan"], case["material"])
            t0 = time.perf_counter()
            scale_mm = _case_scale(spread + SCALE_FLOOR_MM)
            rows.append({**base, "scale": "ensemble", "answerer": "ensemble", "surrogate_s": ensemble_s,
                         "estimate_s": time.perf_counter() - t0, "scale_mm": scale_mm, "ood": ood["outside"],
                         "ood_reasons": " | ".join(ood["reasons"]),
                         "error_mm": answer_error(mean, fe) if fe is not None else np.nan,
                         **{f"bound_{int(c * 100)}_mm": _bound_at(ensemble_bound, c, scale_mm) for c in COVERAGES}})
    table = pd.DataFrame(rows)
    pairs = [(s, a) for s in SCALES for a in ANSWERED_BY] + ([("ensemble", "ensemble")] if members else [])
    methods = [method_scores(table, s, a) for s, a in pairs]
    policies = [policy(table, s, c, t, a) for t in args.tolerances for s, a in pairs for c in COVERAGES]
    for p in policies:  # the pair `predict --tolerance` takes with the default calibration
        chosen = auto.at(p["coverage"]).for_tolerance(p["tolerance_mm"])
        p["default"] = (chosen.scale, chosen.answerer) == (p["scale"], p["answerer"])
    calib = {s: {"plans": c.bound.n, "answerer": c.answerer,
                 **{f"factor_90_{a}": c.bounds[a].factor for a in ANSWERED_BY},
                 **{f"factor_95_{a}": (c.bounds[a].at(0.95).factor if c.bound.n >= min_calibration_cases(0.95)
                                       else None) for a in ANSWERED_BY}}
             for s, c in calibrations.items()}
    if ensemble_bound is not None:
        calib["ensemble"] = {"plans": ensemble_bound.n, "members": len(members), "factor_90": ensemble_bound.factor,
                             "factor_95": (ensemble_bound.at(0.95).factor
                                           if ensemble_bound.n >= min_calibration_cases(0.95) else None)}
    one_row = (table.scale == "constant") & (table.answerer == "baseline")  # one row per case
    warm = table[one_row].dropna(subset=["fe_warm_s"]) if "fe_warm_s" in table else table[:0]
    warm_start = {"cases": int(len(warm)), "cold_s": float(warm.fe_s.mean()), "warm_s": float(warm.fe_warm_s.mean()),
                  "cold_newton": float(warm.fe_newton.mean()), "warm_newton": float(warm.fe_warm_newton.mean()),
                  "max_diff_mm": float(warm.fe_warm_max_diff_mm.max())} if len(warm) else None
    write_result(args.out, table, argv=argv, extra={"methods": methods, "policies": policies,
                                                    "calibration": calib, "tolerances_mm": args.tolerances,
                                                    "auto": {"scale": auto.scale, "answerer": auto.answerer},
                                                    "warm_start": warm_start})
    if args.out.resolve().parent == RESULTS.resolve():
        FIGURES.mkdir(parents=True, exist_ok=True)
        plot(table, args.tolerances[0], FIGURES / f"{args.out.stem}.png")
    with pd.option_context("display.width", 200):
        print(pd.DataFrame(methods).to_string(index=False, float_format=lambda v: f"{v:.3g}"))
        print(pd.DataFrame(policies).to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    return table


if __name__ == "__main__":
    main()
