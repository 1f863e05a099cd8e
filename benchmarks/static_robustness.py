"""Robustness of the static FE over the physiological plan space.

For every combination of resolution x material x sliding model x sampler mode, runs
``--plans`` plans drawn by :func:`toolkit.static.plan.sample_plans` (the lip-sliding paper's ranges,
both segments moved) and records per plan: status (ok / the error's class), wall time,
minimum corner scaled Jacobian of every increment's deformed mesh, increments cut, the
release band used, the fixed nodes of the cut freed (``SimulationOptions.free_cut_radius``),
the error message. Writes ``benchmarks/results/static_robustness_runs.csv`` (one row per run,
appended as runs finish, so an interrupted sweep resumes where it stopped) and
``static_robustness.csv`` (the summary table), each with its provenance sidecar, and prints
the table.

Usage::

    python benchmarks/static_robustness.py --resolutions coarse paper --plans 200
    python benchmarks/static_robustness.py --resolutions fine --materials linear --slidings mucosa+lip --plans 20
"""

from __future__ import annotations

import argparse
import time
import traceback
import warnings
from pathlib import Path

import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

COLUMNS = ["resolution", "material", "sliding", "mode", "max_jaw_closing_mm", "plan", "jaw_closing_mm", "status",
           "seconds", "min_scaled_jacobian", "substeps", "linear_solves", "max_displacement_mm", "release_width_mm",
           "freed_cut_nodes", "message"]


def run_one(phantom, plan, material, sliding, increments):
    from toolkit.static import simulate
    from toolkit.static.simulate import SimulationError

    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = simulate(phantom, plan, increments, material, sliding)
    except SimulationError as exc:
        return {"status": "SimulationError", "seconds": time.perf_counter() - t0, "message": str(exc)[:300]}
    except Exception as exc:  # noqa: BLE001 - the benchmark records every failure
        return {"status": type(exc).__name__, "seconds": time.perf_counter() - t0,
                "message": (str(exc) + " | " + traceback.format_exc(limit=2).replace("\n", " "))[:300]}
    s = res.summary()
    return {"status": "ok", "seconds": time.perf_counter() - t0, "min_scaled_jacobian": s["min_scaled_jacobian"],
            "substeps": s["substeps"], "max_displacement_mm": s["max_displacement_mm"],
            "linear_solves": sum(r["linear_solves"] for r in s["increments_report"]),
            "release_width_mm": s["release_width_mm"], "freed_cut_nodes": s["freed_cut_nodes"], "message": ""}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolutions", nargs="+", default=["coarse", "paper"])
    ap.add_argument("--materials", nargs="+", default=["linear", "neo-hookean"])
    ap.add_argument("--slidings", nargs="+", default=["mucosa+lip", "mucosa", "none"])
    ap.add_argument("--modes", nargs="+", default=["sagittal", "full"])
    ap.add_argument("--plans", type=int, default=200)
    ap.add_argument("--first", type=int, default=0, help="index of the first plan")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--increments", type=int, default=3)
    ap.add_argument("--max-jaw-closing", type=float, default=10.0,
                    help="sample_plans' max_jaw_closing_mm (mm); a negative value keeps every draw")
    ap.add_argument("--retry-failed", action="store_true",
                    help="run again the selected plans that failed (their old rows are dropped)")
    ap.add_argument("--rerun-retried", action="store_true",
                    help="run again the selected plans that needed a wider release band (their old rows are "
                         "dropped)")
    ap.add_argument("--runs", type=Path, default=RESULTS / "static_robustness_runs.csv")
    ap.add_argument("--out", type=Path, default=RESULTS / "static_robustness.csv")
    args = ap.parse_args(argv)

    from tqdm import tqdm

    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.static.boundary import DEFAULT_RELEASE_WIDTH
    from toolkit.static.plan import dental_arch, jaw_closing, sample_plans

    set_threads(1)
    args.runs.parent.mkdir(parents=True, exist_ok=True)
    resumed = args.runs.exists()
    done = pd.read_csv(args.runs, keep_default_na=False) if args.runs.exists() else pd.DataFrame(columns=COLUMNS)
    closing = None if args.max_jaw_closing < 0 else args.max_jaw_closing
    closing_key = -1.0 if closing is None else closing
    rewrite = False
    if args.retry_failed or args.rerun_retried:
        selected = (done.resolution.isin(args.resolutions) & done.material.isin(args.materials)
                    & done.sliding.isin(args.slidings) & done["mode"].isin(args.modes)
                    & (done.max_jaw_closing_mm.astype(float) == closing_key)
                    & done.plan.astype(int).between(args.first, args.first + args.plans - 1))
        again = selected & (((done.status != "ok") & args.retry_failed)
                            | ((pd.to_numeric(done.release_width_mm, errors="coerce") > DEFAULT_RELEASE_WIDTH)
                               & args.rerun_retried))
        rewrite |= bool(again.any())
        done = done[~again]
    if rewrite:
        write_result(args.runs, done[COLUMNS], sidecar=False)
    key = set(zip(done.resolution, done.material, done.sliding, done["mode"], done.max_jaw_closing_mm.astype(float),
                  done.plan.astype(int)))
    for resolution in args.resolutions:
        phantom = face_hex(resolution)
        arch = dental_arch(phantom)
        for mode in args.modes:
            plans = sample_plans(args.first + args.plans, args.seed, mode, phantom=phantom, max_jaw_closing_mm=closing)
            for material in args.materials:
                for sliding in args.slidings:
                    todo = [i for i in range(args.first, args.first + args.plans)
                            if (resolution, material, sliding, mode, closing_key, i) not in key]
                    bar = tqdm(todo, desc=f"{resolution} {material} {sliding} {mode}", leave=False)
                    for i in bar:
                        row = {"resolution": resolution, "material": material, "sliding": sliding, "mode": mode,
                               "max_jaw_closing_mm": closing_key, "plan": i,
                               "jaw_closing_mm": jaw_closing(plans[i], arch),
                               **run_one(phantom, plans[i], material, sliding, args.increments)}
                        pd.DataFrame([row], columns=COLUMNS).to_csv(args.runs, mode="a", index=False,
                                                                    header=not args.runs.exists())
                        if row["status"] != "ok":
                            tqdm.write(f"plan {i}: {row['status']}: {row['message'][:160]}")
    runs = pd.read_csv(args.runs, keep_default_na=False)
    runs["ok"] = runs.status == "ok"
    runs["min_scaled_jacobian"] = pd.to_numeric(runs.min_scaled_jacobian, errors="coerce")
    table = runs.groupby(["resolution", "material", "sliding", "mode", "max_jaw_closing_mm"], sort=False).agg(
        plans=("ok", "size"), completed=("ok", "sum"), median_s=("seconds", "median"), max_s=("seconds", "max"),
        min_sj=("min_scaled_jacobian", "min"),
        wider_band=("release_width_mm",
                    lambda w: int((pd.to_numeric(w, errors="coerce") > DEFAULT_RELEASE_WIDTH).sum())),
        freed_cut=("freed_cut_nodes", lambda f: int((pd.to_numeric(f, errors="coerce") > 0).sum()))).reset_index()
    table["completion"] = table.completed / table.plans
    write_result(args.runs, runs.drop(columns="ok"), resumed=resumed)
    write_result(args.out, table, resumed=resumed)
    with pd.option_context("display.width", 160, "display.max_rows", 200):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"wrote {args.out} and {args.runs}")
    return table


if __name__ == "__main__":
    main()
