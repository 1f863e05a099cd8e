"""Speed/accuracy ladder of the static (orthognathic) simulation.

Every combination of resolution x material x increments x sliding runs the same plan
(the packaged bimaxillary plan scaled by ``--plan-scale``) in a fresh process, which
reports its wall time and peak resident memory. Each run is compared with the
highest-fidelity run of its resolution (Neo-Hookean, 10 increments, mucosa+lip; where
that one is skipped or fails, the best finished run in that order) by the 95th percentile over
all nodes of the nodal displacement difference (``p95_diff_mm``, what ``--tolerance`` bounds) and
by the mean and max difference of the skin-node displacements (mm).

Results go to ``benchmarks/results/static_ladder.csv`` with its provenance sidecar (one row
per run, written atomically after each run; a rerun skips rows already there, so an
interrupted ladder resumes), the displacements to ``benchmarks/work/static_ladder/*.npz``
with the plot ``tradeoff.png`` (error vs wall time), and a table to stdout.

    python benchmarks/static_ladder.py                       # coarse + paper, all options
    python benchmarks/static_ladder.py --resolutions fine --materials linear --increments 1 3
"""

from __future__ import annotations

import argparse
import itertools
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, work_folder, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")

FIDELITY_ORDER = [("neo-hookean", 10), ("neo-hookean", 3), ("linear", 10), ("linear", 3)]


def run_one(resolution: str, material: str, increments: int, sliding: str, plan_scale: float, out: str) -> dict:
    """One simulation in this (fresh) process; saves the final displacements and the skin's node
    ids to ``out``."""
    from toolkit.common import face_hex
    from toolkit.static import SimulationError, default_plan, simulate

    phantom = face_hex(resolution)
    plan = default_plan(phantom).scaled(plan_scale)
    t0 = time.perf_counter()
    row = {"resolution": resolution, "material": material, "increments": increments, "sliding": sliding,
           "nodes": phantom.mesh.n_points}
    try:
        result = simulate(phantom, plan, increments, material, sliding)
    except SimulationError as exc:
        row.update(status="failed", error=str(exc)[:200], wall_time_s=time.perf_counter() - t0)
    else:
        skin = phantom.mesh.node_sets["skin"]
        np.savez_compressed(out, displacement=result.displacement, skin=skin)
        s = result.summary()
        row.update(status="ok", error="", wall_time_s=time.perf_counter() - t0,
                   max_displacement_mm=s["max_displacement_mm"], min_scaled_jacobian=s["min_scaled_jacobian"],
                   max_penetration_mm=s["max_penetration_mm"],
                   linear_solves=sum(r.linear_solves for r in result.reports))
    row["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return row


def _key(r) -> str:
    return f"{r['resolution']}_{r['material']}_{r['increments']}_{r['sliding'].replace('+', '-')}"


def compare(df: pd.DataFrame, folder: Path) -> pd.DataFrame:
    """Add the displacement difference to the best reference of each resolution: its 95th
    percentile over all nodes, and its mean and max over the skin."""
    df = df.copy()
    for col in ("reference", "p95_diff_mm", "skin_mean_diff_mm", "skin_max_diff_mm"):
        df[col] = np.nan if col != "reference" else ""
    for _, group in df.groupby("resolution"):
        ref = None
        for mat, inc in FIDELITY_ORDER:
            hit = group[(group.material == mat) & (group.increments == inc) & (group.sliding == "mucosa+lip")
                        & (group.status == "ok")]
            if len(hit):
                ref = hit.iloc[0]
                break
        if ref is None:
            continue
        reference = np.load(folder / f"{_key(ref)}.npz")
        skin = reference["skin"]
        for i, r in group[group.status == "ok"].iterrows():
            u = np.load(folder / f"{_key(r)}.npz")["displacement"]
            d = np.linalg.norm(u - reference["displacement"], axis=1)
            df.loc[i, "p95_diff_mm"] = np.percentile(d, 95)
            df.loc[i, ["skin_mean_diff_mm", "skin_max_diff_mm"]] = d[skin].mean(), d[skin].max()
            df.loc[i, "reference"] = _key(ref)
    return df


def main(argv=None) -> pd.DataFrame:
    parser = argparse.ArgumentParser(description="static speed/accuracy ladder")
    parser.add_argument("--resolutions", nargs="+", default=["coarse", "paper"])
    parser.add_argument("--materials", nargs="+", default=["linear", "neo-hookean"])
    parser.add_argument("--increments", nargs="+", type=int, default=[1, 3, 10])
    parser.add_argument("--sliding", nargs="+", default=["none", "mucosa", "mucosa+lip"])
    parser.add_argument("--plan-scale", type=float, default=0.5,
                        help="scale of the packaged plan (0.5: a moderate bimaxillary move that stays valid at "
                             "the fine resolution)")
    parser.add_argument("--out", type=Path, default=RESULTS / "static_ladder.csv")
    args = parser.parse_args(argv)
    from toolkit.common.runtime import set_threads

    set_threads(1)  # one thread is fastest on the 2-core AMD EPYC; worker processes inherit it
    folder = work_folder(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    resumed = args.out.exists()
    done = pd.read_csv(args.out) if resumed else pd.DataFrame()
    rows = done.to_dict("records")
    have = {_key(r) for r in rows}
    todo = [c for c in itertools.product(args.resolutions, args.materials, args.increments, args.sliding)
            if _key(dict(zip(("resolution", "material", "increments", "sliding"), c))) not in have]
    from tqdm import tqdm

    # one fresh process per run: isolated peak memory, and 2 cores are used by one run at a time
    with ProcessPoolExecutor(max_workers=1, max_tasks_per_child=1) as pool:
        for combo in tqdm(todo, desc="static ladder"):
            key = _key(dict(zip(("resolution", "material", "increments", "sliding"), combo)))
            rows.append(pool.submit(run_one, *combo, args.plan_scale, str(folder / f"{key}.npz")).result())
            write_result(args.out, pd.DataFrame(rows), sidecar=False)
    df = compare(pd.DataFrame(rows), folder)
    write_result(args.out, df, extra={"plan_scale": args.plan_scale}, resumed=resumed)
    cols = ["resolution", "material", "increments", "sliding", "status", "wall_time_s", "peak_rss_mib",
            "p95_diff_mm", "skin_mean_diff_mm", "skin_max_diff_mm", "min_scaled_jacobian", "max_penetration_mm"]
    with pd.option_context("display.width", 200, "display.max_rows", 500, "display.float_format", "{:.3g}".format):
        print(df[cols].to_string(index=False))
    ok = df[(df.status == "ok") & df.p95_diff_mm.notna()]
    if len(ok):
        from toolkit.common.plotting import plot_tradeoff

        labels = [f"{r.resolution[0]}/{r.material[:3]}/{r.increments}/{r.sliding}" for r in ok.itertuples()]
        plot_tradeoff(ok.wall_time_s.to_numpy(), np.maximum(ok.p95_diff_mm.to_numpy(), 1e-6), labels,
                      ylabel="95th percentile nodal difference to the reference (mm)",
                      title="static ladder (reference: best run per resolution)",
                      path=folder / "tradeoff.png")
    print(f"wrote {args.out} and {folder / 'tradeoff.png'}")
    return df


if __name__ == "__main__":
    main()
