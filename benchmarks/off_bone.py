"""The static simulation on a face whose mucosa lies off its bone, as segmented faces come.

The paper phantom with its bone surfaces moved away from the tissue
(:func:`toolkit.common.phantoms.off_bone.off_bone`: mucosa 2.3 mm median, 4.3 mm at most off its bone)
runs a 5 mm mandibular advance, then plans drawn by :func:`toolkit.static.plan.sample_plans`
in both modes (the lip-sliding paper's ranges), 3 increments, mucosa and lip sliding. Per plan:
status, time, minimum corner scaled Jacobian over the increments, the release band used, and
the offset drift: the largest change, over the increments and the sliding mucosa nodes, of a
node's distance to its moved bone from its pre-operative offset. Writes
``benchmarks/results/off_bone_runs.csv`` (one row per run) and ``off_bone.csv`` (per case and
material), each with its provenance sidecar, and prints the table. ``--thresholds`` runs each
value of ``SimulationOptions.max_mucosa_offset`` (the distance beyond which a mucosa node is left
free instead of sliding).

Usage::

    python benchmarks/off_bone.py --plans 5
    python benchmarks/off_bone.py --resolution coarse --median 5 --p90 15 --max-offset 20 --modes full \
        --plans 8 --materials linear --thresholds inf 10 5 3 --out benchmarks/results/off_bone_far.csv
"""

from __future__ import annotations

import argparse
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/static/", "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/papers.py")


def _distances(face, plan, nodes, bc, x):
    """Distance of ``nodes`` at ``x`` to their bone surface moved by ``plan`` (extended beyond its
    rim), mm."""
    from toolkit.common.analysis.surface_distance import beyond_rim_onto_plane, closest_points

    d = np.zeros(nodes.size)
    for s, name in enumerate(bc.segment_names):
        sel = np.flatnonzero(bc.segment[nodes] == s)
        if sel.size:
            surf = face.segments[name].surface
            moved = plan.motion(name).apply(surf.points)
            cp = closest_points(x[nodes[sel]], moved, surf.cells["tri3"])
            d[sel] = beyond_rim_onto_plane(x[nodes[sel]], cp, moved, surf.cells["tri3"])[0].distance
    return d


def offset_drift(face, plan, result) -> float:
    """Largest |distance to the moved bone - pre-operative offset| of the sliding mucosa, mm."""
    from toolkit.static.boundary import NodeType

    bc = result.boundary
    mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
    n = result.displacements.shape[0] - 1
    d0 = _distances(face, plan.interpolated(0.0), mucosa, bc, result.reference.points)
    return max(float(np.abs(_distances(face, plan.interpolated(k / n), mucosa, bc,
                                       result.reference.points + result.displacements[k]) - d0).max(initial=0.0))
               for k in range(1, n + 1))


def run_one(face, plan, material, increments, max_mucosa_offset):
    from toolkit.static import simulate
    from toolkit.static.simulate import SimulationError, SimulationOptions

    t0 = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            res = simulate(face, plan, increments, material, "mucosa+lip",
                           options=SimulationOptions(max_mucosa_offset=max_mucosa_offset))
    except SimulationError as exc:
        return {"status": "SimulationError", "seconds": time.perf_counter() - t0, "message": str(exc)[:300]}
    s = res.summary()
    return {"status": "ok", "seconds": time.perf_counter() - t0, "min_scaled_jacobian": s["min_scaled_jacobian"],
            "release_width_mm": s["release_width_mm"], "substeps": s["substeps"],
            "offset_drift_mm": offset_drift(face, plan, res), "offset_median_mm": s["mucosa_offset_mm"]["median"],
            "offset_p90_mm": s["mucosa_offset_mm"]["p90"], "offset_max_mm": s["mucosa_offset_mm"]["max"],
            "far_mucosa_nodes": s["far_mucosa_nodes"], "message": ""}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--resolution", default="paper")
    ap.add_argument("--materials", nargs="+", default=["linear", "neo-hookean"])
    ap.add_argument("--modes", nargs="+", default=["sagittal", "full"])
    ap.add_argument("--plans", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--increments", type=int, default=3)
    ap.add_argument("--median", type=float, default=2.5, help="off_bone's median vertex offset (mm)")
    ap.add_argument("--p90", type=float, default=8.0, help="off_bone's 90th percentile vertex offset (mm)")
    ap.add_argument("--max-offset", type=float, default=10.0, help="off_bone's largest vertex offset (mm)")
    ap.add_argument("--thresholds", type=float, nargs="+", default=[5.0],
                    help="SimulationOptions.max_mucosa_offset values to run (mm; inf: every mucosa node slides)")
    ap.add_argument("--out", type=Path, default=RESULTS / "off_bone.csv")
    args = ap.parse_args(argv)

    from tqdm import tqdm

    from toolkit.common.phantoms.off_bone import off_bone
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.static.plan import SurgicalPlan, sample_plans

    set_threads(1)
    face = off_bone(face_hex(args.resolution), args.median, args.p90, args.max_offset)
    cases = [("5 mm mandibular advance", 0, SurgicalPlan.for_phantom(face, distal={"translation_mm": [0, 5, 0]}))]
    for mode in args.modes:
        plans = sample_plans(args.plans, args.seed, mode, phantom=face)
        cases += [(f"sample_plans, {mode}", i, p) for i, p in enumerate(plans)]
    rows = []
    for threshold in args.thresholds:
        for material in args.materials:
            for case, i, plan in tqdm(cases, desc=f"{material}, {threshold:g} mm", leave=False):
                rows.append({"resolution": args.resolution, "vertex_offset_median_mm": args.median,
                             "vertex_offset_p90_mm": args.p90, "max_mucosa_offset_mm": threshold, "case": case,
                             "plan": i, "material": material,
                             **run_one(face, plan, material, args.increments, threshold)})
            if rows[-1]["status"] != "ok":
                tqdm.write(f"{case} {i} {material}: {rows[-1]['message'][:160]}")
    runs = pd.DataFrame(rows)
    runs_path = args.out.with_name(args.out.stem + "_runs.csv")
    write_result(runs_path, runs)
    runs["ok"] = runs.status == "ok"
    keys = ["resolution", "vertex_offset_median_mm", "vertex_offset_p90_mm", "max_mucosa_offset_mm", "case", "material"]
    table = runs.groupby(keys, sort=False).agg(
        plans=("ok", "size"), completed=("ok", "sum"), median_s=("seconds", "median"), max_s=("seconds", "max"),
        min_sj=("min_scaled_jacobian", "min"), wider_band=("release_width_mm", lambda w: int((w > 10.0).sum())),
        max_drift_mm=("offset_drift_mm", "max"), offset_median_mm=("offset_median_mm", "first"),
        offset_p90_mm=("offset_p90_mm", "first"), offset_max_mm=("offset_max_mm", "first"),
        far_mucosa_nodes=("far_mucosa_nodes", "max")).reset_index()
    write_result(args.out, table)
    with pd.option_context("display.width", 200):
        print(table.to_string(index=False, float_format=lambda v: f"{v:.3g}"))
    print(f"wrote {args.out} and {runs_path}")
    return table


if __name__ == "__main__":
    main()
