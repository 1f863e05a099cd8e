"""Speed/accuracy ladder of the impact simulation (the impact paper's scene, 30 mm/s).

Each fidelity option (element order, rigid or deformable ball, mass scaling, time-step
safety factor, and the integrator: explicit dynamics or quasi-static Newton with its residual
tolerance) runs in a
fresh process that reports wall time, peak resident memory and steps. Every run is compared
with the highest-fidelity run of its resolution that finished (explicit, tet10, deformable
ball, no mass scaling, safety 0.9 — or the next best) by the difference in maximum
displacement and maximum von Mises stress, by the 95th percentile over the nodes and frames
of the nodal displacement difference (``p95_displacement_mm``, what ``--tolerance`` bounds;
on the corner nodes, which tet4 and tet10 faces share), and by the RMSE and Pearson
correlation of the skin displacement time series and of the skin's von Mises stress series.
``--scene yielding`` runs the learning database's scene instead
(:func:`toolkit.impact.yielding_scene`: the face held by the skull, 0.36 s, the tissue yielding
from about 35 mm/s).

The scene is mirror-symmetric about the midsagittal plane x = 0 (the phantom's skin nodes map
onto each other exactly and the ball moves along it), and a deformable ball pressed into the
face slides sideways to one side or the other: a symmetry-breaking branch that round-off or the
step size selects (the same quasi-static solver went to -x with 36 load steps and to +x with
144 on the coarse face). So each run is also compared after mirroring its field across x = 0
(``p95_mirrored_mm``, ``rmse_mirrored_mm``, ``pearson_mirrored``), and
``reference_asymmetry_p95_mm`` (``reference_asymmetry_mm``) is the 95th percentile (the RMSE) of
the reference against its own mirror image: the floor of an unmirrored comparison for a run
that took the other branch.

Rows go to ``benchmarks/results/impact_ladder.csv`` (or ``--out``) with its provenance sidecar
(:mod:`_provenance`), written atomically after each run; a rerun skips finished rows (resume).
The fields of each run (``.npz``) and the error-vs-time plot go to
``benchmarks/work/<name of --out>/``.

    python benchmarks/impact_ladder.py --resolutions coarse --duration 1.8
    python benchmarks/impact_ladder.py --resolutions paper --orders 1 2 --balls rigid --mass-scaling 100
    python benchmarks/impact_ladder.py --resolutions coarse --orders 2 --integrators quasi-static
    python benchmarks/impact_ladder.py --resolutions coarse --orders 2 --integrators quasi-static \
        --velocities 20 30 50 --mass-scaling 1 --out benchmarks/results/impact_ladder_velocities.csv
    python benchmarks/impact_ladder.py --resolutions coarse --orders 2 --integrators quasi-static --tolerances 3e-3 1e-2
    python benchmarks/impact_ladder.py --scene yielding --resolutions coarse --orders 2 --balls deformable \
        --mass-scaling 1 --integrators explicit quasi-static --velocities 20 23 26 32 35 38 44 47 50 \
        --out benchmarks/results/impact_ladder_yielding.csv
"""

from __future__ import annotations

import argparse
import functools
import itertools
import resource
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, work_folder, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/impact/", "toolkit/common/fem/", "toolkit/common/meshes/", "toolkit/common/phantoms/",
            "toolkit/common/analysis/surface_distance.py", "toolkit/common/analysis/symmetry.py",
            "toolkit/common/papers.py")

FIDELITY = ["integrator", "order", "ball", "mass_scaling", "safety"]
PAPER_VELOCITY = 30.0  # mm/s, the impact paper's ball
TOLERANCE = 3e-3  # the default Newton tolerance of the quasi-static runs (relative residual)


def _key(r) -> str:
    scene = "" if r.get("scene", "paper") == "paper" else f"{r['scene']}_"
    quasi = "_quasistatic" if r.get("integrator", "explicit") == "quasi-static" else ""
    v = float(r.get("velocity", PAPER_VELOCITY))
    speed = "" if v == PAPER_VELOCITY else f"_v{v:g}"
    tol = float(r.get("tolerance", TOLERANCE))
    if quasi and tol != TOLERANCE:
        quasi += f"_tol{tol:g}"
    return f"{scene}{r['resolution']}_tet{4 if int(r['order']) == 1 else 10}_{r['ball']}" \
           f"_ms{float(r['mass_scaling']):g}_s{float(r['safety']):g}_{float(r['duration']):g}s{speed}{quasi}"


def run_one(resolution, order, ball, mass_scaling, safety, duration, out, integrator="explicit",
            velocity=PAPER_VELOCITY, tolerance=TOLERANCE, scene="paper") -> dict:
    from toolkit.common.errors import AnswerError
    from toolkit.impact import InstabilityError, default_scene, simulate, yielding_scene
    from toolkit.impact.quasi_static import ConvergenceError

    name = scene
    scene = (yielding_scene() if name == "yielding" else default_scene()).with_face(resolution=resolution)
    scene = scene.with_ball(rigid=ball == "rigid", velocity=velocity)
    scene = replace(scene.with_fidelity(order=order, mass_scaling=mass_scaling, safety=safety, integrator=integrator,
                                        tolerance=tolerance), duration=duration, n_frames=18)
    row = {"scene": name, "resolution": resolution, "order": order, "ball": ball, "mass_scaling": mass_scaling,
           "safety": safety, "duration": duration, "integrator": integrator, "velocity": velocity,
           "tolerance": tolerance}
    t0 = time.perf_counter()
    try:
        r = simulate(scene, preview=False)
    except (InstabilityError, ConvergenceError, AnswerError) as exc:
        status = ("unstable" if isinstance(exc, InstabilityError) else
                  "not converged" if isinstance(exc, ConvergenceError) else "failed checks")
        row.update(status=status, error=str(exc)[:200])
    else:
        s = r.summary()
        n_corner = int(r.face.volume_cells[:, :4].max()) + 1
        skin = r.face.node_sets["skin"]
        skin = skin[skin < n_corner]
        np.savez_compressed(out, times=r.times, displacement=r.displacement[:, :n_corner], skin=skin,
                            von_mises=r.von_mises[:, skin])
        row.update(status="ok", error="", face_nodes=r.face.points.shape[0], face_elements=r.face.volume_cells.shape[0],
                   steps=s["steps"], dt_s=s["dt_s"],
                   max_displacement_mm=s["max_displacement_mm"], max_von_mises_mpa=s["max_von_mises_mpa"],
                   energy_error=s["energy_error"], max_energy_error=s["max_energy_error"],
                   added_mass_fraction=s["added_mass_fraction"], max_penetration_mm=s["max_penetration_mm"],
                   kinetic_to_internal=float(r.energies.kinetic.iloc[-1] / max(r.energies.internal.iloc[-1], 1e-30)),
                   newton_iterations=r.stats.get("iterations", 0), step_cuts=r.stats.get("cuts", 0))
    row["wall_time_s"] = time.perf_counter() - t0
    row["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return row


@functools.cache
def _mirror(resolution: str) -> np.ndarray | None:
    """Index of each corner node's mirror image across x = 0 (the lips of the mouth slit, which
    share positions, kept apart), or None when the face is not mirror-symmetric to 1e-6 mm."""
    from toolkit.common.analysis.symmetry import mirror_index
    from toolkit.impact import default_scene
    from toolkit.impact.simulate import face_mesh

    face = face_mesh(default_scene().with_face(resolution=resolution).with_fidelity(order=1))
    corners = np.arange(int(face.volume_cells[:, :4].max()) + 1)
    return mirror_index(face.points[corners], _lip_labels(face, corners))


def _p95(a: np.ndarray, b: np.ndarray) -> float:
    """95th percentile over frames and nodes of the nodal distance between two displacement
    series ``(frames, nodes, 3)``, mm."""
    return float(np.percentile(np.linalg.norm(a - b, axis=-1), 95))


def _lip_labels(face, nodes: np.ndarray) -> np.ndarray:
    """0 for a node on neither lip of the mouth slit, 1 upper, 2 lower."""
    labels = np.zeros(nodes.size, dtype=int)
    for label, name in ((1, "upper_lip_face"), (2, "lower_lip_face")):
        if name in face.node_sets:
            labels[np.isin(nodes, face.node_sets[name])] = label
    return labels


def _agreement(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """RMSE (mm) and Pearson correlation of two displacement series ``(frames, nodes, 3)``."""
    rmse = float(np.sqrt(np.mean((a - b) ** 2)))
    pearson = float(np.corrcoef(a.ravel(), b.ravel())[0, 1]) if a.std() > 0 and b.std() > 0 else np.nan
    return rmse, pearson


def compare(df: pd.DataFrame, folder: Path) -> pd.DataFrame:
    from toolkit.common.analysis.symmetry import mirrored

    df = df.copy()
    for c in ("reference", "d_max_displacement_mm", "d_max_von_mises_mpa", "p95_displacement_mm",
              "rmse_displacement_mm", "pearson_displacement", "p95_mirrored_mm", "rmse_mirrored_mm",
              "pearson_mirrored", "reference_asymmetry_p95_mm", "reference_asymmetry_mm"):
        df[c] = "" if c == "reference" else np.nan
    order = [(2, "deformable", 1.0), (2, "deformable", 10.0), (2, "rigid", 1.0), (1, "deformable", 1.0),
             (2, "rigid", 10.0), (2, "deformable", 100.0), (2, "rigid", 100.0)]
    if "scene" not in df.columns:
        df["scene"] = "paper"
    df["scene"] = df["scene"].fillna("paper")
    for c in ("rmse_von_mises_mpa", "pearson_von_mises"):
        df[c] = np.nan
    for (_, res, _, _), g in df.groupby(["scene", "resolution", "duration", "velocity"]):
        ok = g[g.status == "ok"]
        explicit = ok[ok.integrator == "explicit"]
        ref = None
        for o, b, ms in order:
            same = (explicit.order == o) & (explicit.ball == b) & (explicit.mass_scaling == ms)
            hit = explicit[same].sort_values("safety")
            if len(hit):
                ref = hit.iloc[0]
                break
        if ref is None:
            continue
        R = np.load(folder / f"{_key(ref)}.npz")
        B, b_vm, skin = R["displacement"], R["von_mises"], R["skin"]
        b = B[:, skin]
        mirror = _mirror(res)
        for i, r in ok.iterrows():
            A = np.load(folder / f"{_key(r)}.npz")
            a = A["displacement"][:, skin]
            df.loc[i, "p95_displacement_mm"] = _p95(A["displacement"], B)
            df.loc[i, ["rmse_von_mises_mpa", "pearson_von_mises"]] = _agreement(A["von_mises"], b_vm)
            df.loc[i, "reference"] = _key(ref)
            df.loc[i, "d_max_displacement_mm"] = r.max_displacement_mm - ref.max_displacement_mm
            df.loc[i, "d_max_von_mises_mpa"] = r.max_von_mises_mpa - ref.max_von_mises_mpa
            df.loc[i, ["rmse_displacement_mm", "pearson_displacement"]] = _agreement(a, b)
            if mirror is not None:
                flipped = mirrored(A["displacement"], mirror)
                df.loc[i, "p95_mirrored_mm"] = _p95(flipped, B)
                df.loc[i, ["rmse_mirrored_mm", "pearson_mirrored"]] = _agreement(flipped[:, skin], b)
                df.loc[i, "reference_asymmetry_p95_mm"] = _p95(mirrored(B, mirror), B)
                df.loc[i, "reference_asymmetry_mm"] = _agreement(mirrored(B, mirror)[:, skin], b)[0]
    return df


def main(argv=None) -> pd.DataFrame:
    p = argparse.ArgumentParser(description="impact speed/accuracy ladder")
    p.add_argument("--resolutions", nargs="+", default=["coarse"])
    p.add_argument("--orders", nargs="+", type=int, default=[1, 2])
    p.add_argument("--balls", nargs="+", default=["rigid", "deformable"])
    p.add_argument("--mass-scaling", nargs="+", type=float, default=[1.0, 10.0, 100.0])
    p.add_argument("--safety", nargs="+", type=float, default=[0.9])
    p.add_argument("--integrators", nargs="+", default=["explicit"], choices=["quasi-static", "explicit"],
                   help="quasi-static: Newton load steps (mass scaling and safety do not apply; run once)")
    p.add_argument("--scene", default="paper", choices=["paper", "yielding"],
                   help="the impact paper's scene (face held at its lower band), or the learning database's "
                        "(held by the skull, 0.36 s)")
    p.add_argument("--duration", type=float, help="simulated time, s (default: the scene's, 1.8 or 0.36)")
    p.add_argument("--velocities", nargs="+", type=float, default=[PAPER_VELOCITY],
                   help="ball speeds, mm/s (the impact paper: 30; its range 20-50); each speed has its own reference")
    p.add_argument("--tolerances", nargs="+", type=float, default=[TOLERANCE],
                   help="Newton tolerances of the quasi-static runs (relative residual; Fidelity.tolerance)")
    p.add_argument("--out", type=Path, default=RESULTS / "impact_ladder.csv")
    args = p.parse_args(argv)
    if args.duration is None:
        from toolkit.impact.scene import YIELDING_DURATION

        args.duration = YIELDING_DURATION if args.scene == "yielding" else 1.8
    from toolkit.common.runtime import set_threads

    set_threads(1)  # one thread is fastest on the 2-core AMD EPYC; worker processes inherit it
    folder = work_folder(args.out)
    folder.mkdir(parents=True, exist_ok=True)
    resumed = args.out.exists()
    rows = pd.read_csv(args.out).to_dict("records") if resumed else []
    have = {_key(r) for r in rows}
    combos = [dict(scene=args.scene, resolution=r, order=o, ball=b, mass_scaling=m, safety=s, duration=args.duration,
                   integrator=i, velocity=v, tolerance=tol)
              for r, o, b, m, s, i, v, tol in itertools.product(args.resolutions, args.orders, args.balls,
                                                                args.mass_scaling, args.safety, args.integrators,
                                                                args.velocities, args.tolerances)
              if (i == "explicit" and tol == args.tolerances[0])
              or (i == "quasi-static" and m == args.mass_scaling[0] and s == args.safety[0])]
    for c in combos:  # no inertia in the quasi-static path: one run, recorded without mass scaling
        if c["integrator"] == "quasi-static":
            c["mass_scaling"], c["safety"] = 1.0, 0.9
    # cheapest first, so an interrupted ladder has the fast rungs
    combos.sort(key=lambda c: (c["resolution"] != "coarse", -c["mass_scaling"], c["order"], c["ball"] != "rigid"))
    todo = [c for c in combos if _key(c) not in have]
    from tqdm import tqdm

    with ProcessPoolExecutor(max_workers=1, max_tasks_per_child=1) as pool:
        for c in tqdm(todo, desc="impact ladder"):
            rows.append(pool.submit(run_one, **c, out=str(folder / f"{_key(c)}.npz")).result())
            write_result(args.out, pd.DataFrame(rows), sidecar=False)
    df = compare(pd.DataFrame(rows), folder)
    write_result(args.out, df, resumed=resumed)
    cols = ["scene", "resolution", "velocity", "integrator", "tolerance", "order", "ball", "mass_scaling", "safety",
            "status", "steps",
            "wall_time_s",
            "peak_rss_mib", "newton_iterations", "step_cuts", "max_displacement_mm", "max_von_mises_mpa",
            "energy_error", "d_max_displacement_mm",
            "d_max_von_mises_mpa", "p95_displacement_mm", "rmse_displacement_mm", "pearson_displacement",
            "p95_mirrored_mm", "rmse_mirrored_mm", "pearson_mirrored", "reference_asymmetry_p95_mm",
            "reference_asymmetry_mm", "rmse_von_mises_mpa", "pearson_von_mises"]
    cols = [c for c in cols if c in df.columns]
    with pd.option_context("display.width", 250, "display.max_rows", 200, "display.float_format", "{:.4g}".format):
        print(df[cols].to_string(index=False))
    ok = df[(df.status == "ok") & (df.p95_displacement_mm > 0)]  # the references themselves are not plotted
    if len(ok):
        from toolkit.common.plotting import plot_tradeoff

        labels = [f"{r.resolution[0]}/tet{4 if r.order == 1 else 10}/{r.ball[0]}/"
                  + (f"quasi-static {r.tolerance:g}" if r.integrator == "quasi-static" else f"ms{r.mass_scaling:g}")
                  for r in ok.itertuples()]
        plot_tradeoff(ok.wall_time_s.to_numpy(), ok.p95_displacement_mm.to_numpy(), labels,
                      ylabel="95th percentile nodal displacement difference (mm)", title="impact ladder",
                      path=folder / "tradeoff.png")
    print(f"wrote {args.out}")
    return df


if __name__ == "__main__":
    main()
