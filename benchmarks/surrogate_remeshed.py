"""PointNet++ on a face it has never seen, meshed differently: an unseen phantom subject remeshed by
``toolkit mesh``, against the FE on that mesh, beside the influence-matrix solution of that mesh alone.

PointNet++ reads a point cloud, so unlike the node-indexed baselines (POD, linear + POD residual) it can
predict on a mesh of another topology (``Surrogate.predict_plan(..., any_mesh=True)``, command line
``toolkit static predict --any-mesh``). Stages (each resumable; rerun the same command to continue):

1. ``database``: ``--plans`` sampled plans (sagittal, the lip-sliding paper's ranges) on each of
   ``--subjects`` paper phantom subjects -> ``work/static_paper_subjects.h5`` (the file
   ``static_surrogate.py`` makes with the same options);
2. ``model``: the default PointNet++ (hard boundary values over the linear prior) trained on every
   subject of it within ``--max-minutes`` -> ``work/remeshed_model/``;
3. ``unseen``: subject ``--test-subject`` (``FaceShape.sample(k)``, outside the database), as its
   hexahedral phantom and as its surfaces meshed by :func:`toolkit.mesh.mesh_face` (``--size``,
   tet10); ``--test-plans`` plans on both, the FE of each cached in ``work/remeshed_fe/``;
4. ``face``: ``--face-plans`` plans on the remeshed face itself -> a database and the default
   PointNet++ trained on it (``--face-minutes``): what a surrogate of the patient's own face gives;
5. scores of the networks and of the prior (the influence matrix of the same mesh) against the FE
   of the same mesh: per plan the post-operative displacement's error at every node (mean, 95th
   percentile) and at the lip nodes (mean), and the time per plan (the influence matrix built once
   per mesh, its time in ``prior_build_s``).

Writes ``benchmarks/results/surrogate_remeshed.csv`` (one row per mesh, method and plan) with its
provenance sidecar; prints the summary.

    python benchmarks/surrogate_remeshed.py                       # 4 x 25 plans, 8 min, 10 test plans
    python benchmarks/surrogate_remeshed.py --subjects 2 --plans 5 --max-minutes 1 --test-plans 2 --size 9
"""

from __future__ import annotations

import argparse
import hashlib
import time
from pathlib import Path

import numpy as np
import pandas as pd
from _provenance import RESULTS, WORK, write_result

#: the code this benchmark measures: a result is stale once any of these changed after its commit
MEASURES = ("toolkit/mesh/", "toolkit/static/", "toolkit/common/training/", "toolkit/common/fem/",
            "toolkit/common/meshes/", "toolkit/common/phantoms/", "toolkit/common/analysis/",
            "toolkit/common/papers.py")


def add_training_arguments(ap: argparse.ArgumentParser) -> None:
    """The options :func:`stage_database` and :func:`stage_model` read (``surrogate_trust.py`` shares them)."""
    ap.add_argument("--subjects", type=int, default=4, help="training phantom subjects")
    ap.add_argument("--plans", type=int, default=25, help="plans per training subject")
    ap.add_argument("--max-minutes", type=float, default=8.0, help="training time")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--suffix", default="", help="suffix of the work files (a small run beside the default one)")


def stage_database(args) -> Path:
    from toolkit.static.database import DatabaseConfig, build_database

    WORK.mkdir(parents=True, exist_ok=True)
    path = WORK / f"static_paper_subjects{args.suffix}.h5"
    build_database(path, DatabaseConfig("paper", args.subjects, args.plans, "sagittal", seed=args.seed),
                   workers=args.workers)
    return path


def stage_model(args, db_path: Path):
    from toolkit.static.surrogate import Surrogate, SurrogateConfig, train_surrogate

    out = WORK / f"remeshed_model{args.suffix}"
    if (out / "model.pt").exists():
        return Surrogate.load(out)
    config = SurrogateConfig(max_seconds=60 * args.max_minutes, seed=args.seed)
    return train_surrogate(db_path, config, out=out, resume=(out / "checkpoint.pt").exists())


def stage_face(args, phantom) -> tuple[Path, dict]:
    """The unseen subject's surfaces meshed once and kept (fTetWild differs from run to run):
    ``work/remeshed_face_s<k>_<size>/face.vtu`` and its bone files."""
    from toolkit.common import write
    from toolkit.mesh import mesh_face
    from toolkit.mesh.phantom import phantom_surfaces, write_surfaces

    folder = WORK / f"remeshed_face_s{args.test_subject}_{args.size:g}{args.suffix}"
    face_file = folder / "face.vtu"
    surfaces = phantom_surfaces(phantom)
    files = write_surfaces(folder / "surfaces", surfaces)
    if not face_file.exists():
        face = mesh_face(surfaces.tissue, surfaces.bones, surfaces.commissures, size_mm=args.size, order=2)
        write(face_file, face.mesh)
    return face_file, {k: files[k] for k in ("lefort", "distal", "proximal_left", "proximal_right")}


def face_database_path(args) -> Path:
    return WORK / f"remeshed_face_db_s{args.test_subject}_{args.size:g}{args.suffix}.h5"


def stage_face_model(args, face_file: Path, bones: dict, phantom):
    """A database of ``--face-plans`` plans on the remeshed face itself (the phantom's condyles, which
    lie outside its tissue) and the default PointNet++ trained on it within ``--face-minutes``."""
    from toolkit.static.database import DatabaseConfig, build_database
    from toolkit.static.surrogate import Surrogate, SurrogateConfig, train_surrogate

    db = face_database_path(args)
    config = DatabaseConfig.for_mesh(face_file, bones, phantom.condyles, plans=args.face_plans, mode="sagittal",
                                    seed=args.seed)
    build_database(db, config, workers=args.workers)
    out = WORK / f"remeshed_face_model{args.suffix}"
    if (out / "model.pt").exists():
        return Surrogate.load(out)
    config = SurrogateConfig(max_seconds=60 * args.face_minutes, seed=args.seed)
    return train_surrogate(db, config, out=out, resume=(out / "checkpoint.pt").exists())


def prior_only(model, mesh, segments, plan, increments: int, sliding: str) -> tuple[np.ndarray, float, float]:
    """The linear influence-matrix solution of ``mesh`` increment by increment, as the network's
    prior sees it: cumulative displacement ``(n, 3)`` mm, seconds, and the seconds the matrix took
    to build (once per mesh; the model's cache shares it with the network)."""
    from toolkit.static.database import bone_increment
    from toolkit.static.simulate import boundary_conditions

    bc, _ = boundary_conditions(mesh, segments, sliding)
    im = model.prior(mesh, bc.types)
    t0 = time.perf_counter()
    X, U, previous = mesh.points, np.zeros_like(mesh.points), None
    for p in plan.increments(increments):
        prescribed = np.where((bc.types == 1)[:, None], bone_increment(X + U, bc, p, previous), 0.0)
        U = U + im.predict(prescribed)
        previous = p
    return U, time.perf_counter() - t0, im.seconds


def errors(pred: np.ndarray, fe: np.ndarray, lips: np.ndarray) -> dict:
    e = np.linalg.norm(pred - fe, axis=1)
    return {"mean_error_mm": float(e.mean()), "p95_error_mm": float(np.percentile(e, 95)),
            "lips_mean_error_mm": float(e[lips].mean()),
            "fe_mean_displacement_mm": float(np.linalg.norm(fe, axis=1).mean())}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_training_arguments(ap)
    ap.add_argument("--test-subject", type=int, default=7, help="unseen subject k (FaceShape.sample(k))")
    ap.add_argument("--test-plans", type=int, default=10)
    ap.add_argument("--size", type=float, default=7.0, help="element size of the remeshed face, mm")
    ap.add_argument("--face-plans", type=int, default=20,
                    help="plans of a database on the remeshed face itself, for a model trained on that face (0: none)")
    ap.add_argument("--face-minutes", type=float, default=8.0, help="training time of that model")
    ap.add_argument("--out", type=Path, default=RESULTS / "surrogate_remeshed.csv")
    args = ap.parse_args(argv)

    from toolkit.common.phantoms.phantom import FaceShape, face_hex
    from toolkit.common.runtime import set_threads
    from toolkit.static import load_case
    from toolkit.static.plan import sample_plans

    set_threads(1)
    model = stage_model(args, stage_database(args))
    data = model.bundle.data["database"]
    phantom = face_hex("paper", FaceShape.sample(args.test_subject))
    face_file, bones = stage_face(args, phantom)
    face_model = stage_face_model(args, face_file, bones, phantom) if args.face_plans else None
    if face_model is not None:
        from toolkit.common.training.database import read_index

        completed = len(read_index(face_database_path(args), "index"))
        face_method = f"PointNet++ trained on this face ({completed} of {args.face_plans} plans completed)"
    plans = sample_plans(args.test_plans, np.random.default_rng([args.seed, args.test_subject]), "sagittal",
                         phantom=phantom)
    cache = WORK / f"remeshed_fe{args.suffix}"
    cache.mkdir(parents=True, exist_ok=True)
    tag = hashlib.sha1(face_file.read_bytes()).hexdigest()[:8]
    rows = []
    for i, plan in enumerate(plans):
        for mesh_name, case in (("phantom hex8", load_case(resolution="paper", shape=phantom.shape, plan=plan)),
                                (f"remeshed tet10 {args.size:g} mm", load_case(face_file, plan=plan, bones=bones))):
            own = mesh_name.startswith("remeshed")
            kind = f"remeshed-{args.size:g}-{tag}" if own else "phantom"
            file = cache / f"s{args.test_subject}-{kind}-p{i}.npz"
            if file.exists():
                fe, fe_s = np.load(file)["u"], float(np.load(file)["seconds"])
            else:
                t0 = time.perf_counter()
                try:
                    res = case.simulate(increments=data["increments"], material=data["material"],
                                        sliding=data["sliding"])
                except Exception as exc:  # noqa: BLE001 - recorded
                    rows.append({"mesh": mesh_name, "plan": i, "method": "FE", "status": type(exc).__name__})
                    continue
                fe, fe_s = res.displacement, time.perf_counter() - t0
                np.savez(file, u=fe, seconds=fe_s)
            mesh = case.mesh
            lips = np.unique(np.concatenate([mesh.node_sets[k] for k in ("lip_sliding", "upper_lip_face",
                                                                        "lower_lip_face") if k in mesh.node_sets]))
            base = {"mesh": mesh_name, "nodes": mesh.n_points, "plan": i, "status": "ok"}
            rows.append({**base, "method": "FE", "seconds": fe_s})
            prior, prior_s, build_s = prior_only(model, mesh, case.segments, plan, data["increments"],
                                                 data["sliding"])
            t0 = time.perf_counter()
            net = model.predict_plan(case.subject, plan, segments=case.segments, any_mesh=True).displacement
            rows.append({**base, "method": "PointNet++ (hard + prior)", "seconds": time.perf_counter() - t0,
                         "prior_build_s": build_s, **errors(net, fe, lips)})
            rows.append({**base, "method": "influence matrix (the prior alone)", "seconds": prior_s,
                         "prior_build_s": build_s, **errors(prior, fe, lips)})
            if own and face_model is not None:
                t0 = time.perf_counter()
                net = face_model.predict_plan(case.subject, plan, segments=case.segments).displacement
                rows.append({**base, "method": face_method,
                             "seconds": time.perf_counter() - t0, **errors(net, fe, lips)})
            print({k: (round(v, 3) if isinstance(v, float) else v) for k, v in rows[-2].items()}, flush=True)
    table = pd.DataFrame(rows)
    write_result(args.out, table, argv=argv)
    summary = table[table.status == "ok"].groupby(["mesh", "method"], sort=False).agg(
        plans=("plan", "size"), mean_error_mm=("mean_error_mm", "mean"), p95_error_mm=("p95_error_mm", "mean"),
        lips_mean_error_mm=("lips_mean_error_mm", "mean"), seconds=("seconds", "median"))
    with pd.option_context("display.width", 200):
        print(summary.to_string(float_format=lambda v: f"{v:.3g}"))
    return table


if __name__ == "__main__":
    main()
