"""Command line: ``toolkit demo``, ``toolkit phantom``, ``toolkit static ...``, ``toolkit impact ...``.

Only this module prints; the library raises, warns or logs.
"""

from __future__ import annotations

import argparse
import json
import logging
import sys
import time
from contextlib import contextmanager
from pathlib import Path

__all__ = ["main", "build_parser"]


def _add_common(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--threads", type=int, default=None,
                        help="BLAS/torch threads (default: TOOLKIT_NUM_THREADS or 1; 1 is fastest on 2 cores)")
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="toolkit",
        description="Facial soft-tissue biomechanics: phantoms, orthognathic FEM, ball-impact FEM, surrogates.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True

    demo = sub.add_parser("demo", help="build, validate and write the coarse phantoms with previews",
                          description="Build the coarse face (hex8, tet10) and ball phantoms, check every element, "
                                      "and write them as Abaqus .inp and .vtu with PNG previews.")
    demo.add_argument("--out", required=True, type=Path, help="output folder")
    demo.add_argument("--resolution", default="coarse", choices=["coarse", "paper", "fine"],
                      help="phantom resolution (default coarse)")
    demo.add_argument("--no-render", action="store_true", help="skip the PNG previews")
    _add_common(demo)
    demo.set_defaults(func=_cmd_demo)

    ph = sub.add_parser("phantom", help="write one phantom mesh",
                        description="Build one phantom and write it (format from the suffix: .vtu, .xdmf, .inp).")
    ph.add_argument("kind", choices=["face-hex", "face-tet4", "face-tet10", "ball-tet4", "ball-tet10"])
    ph.add_argument("--resolution", default="coarse", choices=["coarse", "paper", "fine"])
    ph.add_argument("--seed", type=int, default=None,
                    help="draw a random subject (FaceShape.sample) instead of the nominal face")
    ph.add_argument("--mouth-open", type=float, default=None, help="lip gap at the skin, mm (0-12)")
    ph.add_argument("--out", required=True, type=Path, help="output mesh file")
    ph.add_argument("--preview", type=Path, default=None, help="also render a PNG here")
    _add_common(ph)
    ph.set_defaults(func=_cmd_phantom)

    st = sub.add_parser("static", help="orthognathic-surgery workflow (the lip-sliding paper)",
                        description="Static workflow: incremental FEM of the face after orthognathic surgery.")
    st_sub = st.add_subparsers(dest="static_command", metavar="STATIC_COMMAND")
    st_sub.required = True
    sim = st_sub.add_parser("simulate", help="simulate a surgical plan on a face",
                            description="Run the incremental FE simulation (mucosa and lip sliding) and write "
                                        "result.vtu (reference mesh + displacement), postop.vtu (post-operative "
                                        "face), increments.xdmf, summary.json and preview.png.")
    src = sim.add_mutually_exclusive_group()
    src.add_argument("--mesh", type=Path, help="face mesh (.inp/.vtu/.xdmf) with the phantom's node sets")
    src.add_argument("--resolution", default="coarse", choices=["coarse", "paper", "fine"],
                     help="built-in phantom resolution (default coarse)")
    sim.add_argument("--plan", type=Path, help="plan (.toml/.json); default: the packaged bimaxillary plan")
    sim.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE",
                     help="bone surface of a segment (lefort, distal, proximal_left, proximal_right, skull) as "
                          "STL/OBJ/PLY/VTK/VTU/OFF in mm, e.g. --bone lefort=maxilla.stl; repeatable. Without it a "
                          "--mesh run rebuilds the surfaces from the mesh's bone-side faces")
    sim.add_argument("--increments", type=int, default=3, help="number of increments (default 3, the lip-sliding paper)")
    sim.add_argument("--material", default="linear", choices=["linear", "neo-hookean"])
    sim.add_argument("--sliding", default="mucosa+lip", choices=["none", "mucosa", "mucosa+lip"])
    sim.add_argument("--solver", default="auto", choices=["auto", "superlu", "amg", "cholmod"])
    sim.add_argument("--force", action="store_true", help="accept movements beyond twice the physiological range")
    sim.add_argument("--out", required=True, type=Path, help="output folder")
    sim.add_argument("--no-preview", action="store_true", help="skip preview.png")
    _add_common(sim)
    sim.set_defaults(func=_cmd_static_simulate)

    ds = st_sub.add_parser("dataset", help="generate the surrogate's learning database",
                           description="Simulate sampled plans on phantom subjects; every increment is a learning "
                                       "sample (the PointNet++ paper). Resumable: a rerun skips finished simulations; failures "
                                       "are recorded with their reason. Ctrl-C loses no finished simulation.")
    ds.add_argument("--resolution", default="coarse", choices=["coarse", "paper", "fine"])
    ds.add_argument("--subjects", type=int, default=1, help="phantom subjects (0: default shape; k: FaceShape.sample(k))")
    ds.add_argument("--plans", type=int, required=True, help="plans per subject")
    ds.add_argument("--mode", default="sagittal", choices=["sagittal", "full"], help="plan directions")
    ds.add_argument("--increments", type=int, default=3)
    ds.add_argument("--material", default="linear", choices=["linear", "neo-hookean"])
    ds.add_argument("--sliding", default="mucosa+lip", choices=["none", "mucosa", "mucosa+lip"])
    ds.add_argument("--poisson-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                    help="draw Poisson's ratio per simulation (for models with material channels)")
    ds.add_argument("--seed", type=int, default=0)
    _add_database_run(ds, "simulations")
    _add_common(ds)
    ds.set_defaults(func=_cmd_static_dataset)

    tr = st_sub.add_parser("train", help="train the PointNet++ surrogate on a database",
                           description="Train PointNet++ (the PointNet++ paper) on a static database; writes model.pt and "
                                       "config.json (checkpoint.pt while training; --resume continues it).")
    tr.add_argument("--data", required=True, type=Path)
    tr.add_argument("--out", required=True, type=Path, help="model directory")
    tr.add_argument("--variant", default="explicit", choices=["explicit", "implicit", "hard"],
                    help="boundary types as inputs (explicit, the PointNet++ paper), none (implicit), or explicit with exact "
                         "boundary values (hard)")
    tr.add_argument("--extra-channels", action="store_true", help="mucosa/lip one-hot, jaw side, mucosa bone motion")
    tr.add_argument("--material-channels", action="store_true", help="Poisson's ratio per node")
    tr.add_argument("--linear-prior", action="store_true",
                    help="learn the residual over the linear influence-matrix solution (given as input, added back)")
    tr.add_argument("--network", default="small", choices=["paper", "small", "tiny"])
    tr.add_argument("--test-subjects", type=int, nargs="*", default=None,
                    help="hold these subjects out for testing (default: 70/10/20 split by simulation)")
    tr.add_argument("--epochs", type=int, default=100)
    tr.add_argument("--batch-size", type=int, default=8)
    tr.add_argument("--lr", type=float, default=1e-3)
    tr.add_argument("--lr-schedule", default="constant", choices=["constant", "cosine"],
                    help="cosine: decay to 1%% of --lr over the epochs (or over --max-minutes when given)")
    tr.add_argument("--max-minutes", type=float, default=None)
    tr.add_argument("--seed", type=int, default=0)
    tr.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    tr.add_argument("--resume", action="store_true")
    _add_common(tr)
    tr.set_defaults(func=_cmd_static_train)

    ev = st_sub.add_parser("evaluate", help="score a surrogate on a database",
                           description="Mean Euclidean nodal error per sample (all, free, lips), inference and FE "
                                       "times; writes metrics.json, per_sample.csv and error_map.png.")
    ev.add_argument("--model", required=True, type=Path)
    ev.add_argument("--data", required=True, type=Path)
    ev.add_argument("--out", required=True, type=Path)
    ev.add_argument("--device", default="cpu")
    ev.add_argument("--no-render", action="store_true")
    _add_common(ev)
    ev.set_defaults(func=_cmd_static_evaluate)

    pr = st_sub.add_parser("predict", help="predict a plan with a surrogate",
                           description="Run a plan with the surrogate instead of the FE; writes the files of "
                                       "`toolkit static simulate`.")
    pr.add_argument("--model", required=True, type=Path)
    pr.add_argument("--plan", type=Path, help="plan (.toml/.json); default: the packaged bimaxillary plan")
    psrc = pr.add_mutually_exclusive_group()
    psrc.add_argument("--mesh", type=Path, help="face mesh with the phantom's node sets (needs --plan)")
    psrc.add_argument("--resolution", default=None, choices=["coarse", "paper", "fine"],
                      help="built-in phantom (default: the training database's)")
    pr.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE", help="as for simulate")
    pr.add_argument("--device", default="cpu")
    pr.add_argument("--out", required=True, type=Path)
    pr.add_argument("--no-preview", action="store_true")
    _add_common(pr)
    pr.set_defaults(func=_cmd_static_predict)

    im = sub.add_parser("impact", help="ball-impact workflow (the impact paper)",
                        description="Impact workflow: explicit elastoplastic simulation of a ball pressed into the face.")
    im_sub = im.add_subparsers(dest="impact_command", metavar="IMPACT_COMMAND")
    im_sub.required = True
    isim = im_sub.add_parser("simulate", help="run an impact scene",
                             description="Run the simulation (explicit or quasi-static) and write face.xdmf (displacement, von_mises), "
                                         "ball.xdmf (deformable ball), history.h5, summary.json and preview.png.")
    isim.add_argument("--scene", type=Path, help="scene TOML (default: the impact paper's scene)")
    isim.add_argument("--velocity", type=float, help="ball velocity, mm/s (the impact paper: 20-50)")
    isim.add_argument("--resolution", choices=["coarse", "paper"], help="face resolution")
    isim.add_argument("--ball", choices=["deformable", "rigid"], help="ball model")
    isim.add_argument("--order", type=int, choices=[1, 2], help="tetrahedron order (1: tet4, 2: tet10)")
    isim.add_argument("--mass-scaling", type=float, help="density factor >= 1 (longer stable steps)")
    isim.add_argument("--integrator", choices=["explicit", "implicit"],
                      help="explicit dynamics (default) or quasi-static Newton load steps")
    isim.add_argument("--duration", type=float, help="simulated time, s (default 1.8)")
    isim.add_argument("--out", required=True, type=Path, help="output folder")
    isim.add_argument("--no-preview", action="store_true")
    _add_common(isim)
    isim.set_defaults(func=_cmd_impact_simulate)

    ids = im_sub.add_parser(
        "dataset", help="build the learning database (one simulation per velocity)",
        description="Simulate the scene at every training and held-out velocity and store the per-node "
                    "displacement and von Mises time series in one resumable HDF5 file (rerun to resume; failures "
                    "are recorded). Default scene: the face held by the skull, 0.36 s (yielding_scene).")
    ids.add_argument("--velocities", type=_floats, default=None,
                     help="training velocities, mm/s, comma-separated (default the impact paper's 20,26,32,38,44,50)")
    ids.add_argument("--held-out", type=_floats, default=None,
                     help="held-out velocities, mm/s (default: midpoints of every other gap, 23,35,47); '' for none")
    ids.add_argument("--scene", type=Path, help="scene TOML (default: the skull-held yielding scene)")
    ids.add_argument("--resolution", choices=["coarse", "paper"], help="face resolution")
    ids.add_argument("--ball", choices=["deformable", "rigid"], help="ball model")
    ids.add_argument("--order", type=int, choices=[1, 2], help="tetrahedron order (1: tet4, 2: tet10)")
    ids.add_argument("--mass-scaling", type=float, help="density factor >= 1 (longer stable steps)")
    ids.add_argument("--duration", type=float, help="simulated time, s")
    _add_database_run(ids, "velocities")
    _add_common(ids)
    ids.set_defaults(func=_cmd_impact_dataset)

    itr = im_sub.add_parser("train", help="train a surrogate on a database",
                            description="Train the the impact paper LSTM, the stronger LSTM or the non-recurrent baseline; "
                                        "writes model.pt, config.json (with the scalers) and checkpoint.pt.")
    itr.add_argument("--data", required=True, type=Path, help="database (.h5) from `toolkit impact dataset`")
    itr.add_argument("--out", required=True, type=Path, help="model directory")
    itr.add_argument("--config", default="paper", choices=["paper", "strong", "baseline", "seed"])
    itr.add_argument("--split", default="random", choices=["random", "velocity"],
                     help="random: 76%% of the items train (the impact paper); velocity: held-out velocities are the test set")
    itr.add_argument("--device", default="cpu", help="cpu (default), cuda, cuda:N or auto")
    itr.add_argument("--seed", type=int, default=0, help="weights, batch order and split (default 0)")
    itr.add_argument("--epochs", type=int, default=None, help="maximum epochs (default: the configuration's)")
    itr.add_argument("--max-minutes", type=float, default=None, help="training time limit (default 15)")
    itr.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")
    _add_common(itr)
    itr.set_defaults(func=_cmd_impact_train)

    iev = im_sub.add_parser("evaluate", help="score a model on its test split",
                            description="RMSE, Pearson and NRMSE of displacement and von Mises on the model's test "
                                        "split; writes metrics.json, timeseries.png and fields.png.")
    iev.add_argument("--model", required=True, type=Path, help="model directory")
    iev.add_argument("--data", required=True, type=Path, help="the database it was trained on")
    iev.add_argument("--out", required=True, type=Path, help="output folder")
    iev.add_argument("--split", choices=["random", "velocity"], default=None,
                     help="test split (default: the one the model was trained with)")
    iev.add_argument("--nodes", type=_ints, default=None, help="node ids for timeseries.png (comma-separated)")
    iev.add_argument("--frames", type=_ints, default=None, help="frame indices for fields.png (comma-separated)")
    _add_common(iev)
    iev.set_defaults(func=_cmd_impact_evaluate)

    ipr = im_sub.add_parser("predict", help="predict the database's scene at a velocity",
                            description="Whole-face displacement and von Mises time series at VELOCITY; writes "
                                        "face.xdmf, summary.json and scene.toml (run its FE with "
                                        "`toolkit impact simulate --scene OUT/scene.toml`).")
    ipr.add_argument("--model", required=True, type=Path, help="model directory")
    ipr.add_argument("--velocity", required=True, type=float, help="ball velocity, mm/s")
    ipr.add_argument("--out", required=True, type=Path, help="output folder")
    _add_common(ipr)
    ipr.set_defaults(func=_cmd_impact_predict)
    return parser


def _torch_threads(args) -> None:
    """torch picks its thread count at import: apply --threads (default 1) again once it is loaded."""
    import torch  # noqa: F401

    from toolkit.common.runtime import set_threads

    set_threads(args.threads)


def _floats(text: str) -> list[float]:
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated numbers, got {text!r}") from None


def _ints(text: str) -> list[int]:
    try:
        return [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def _impact_scene(args, base=None):
    from dataclasses import replace

    from toolkit.impact.scene import Scene, default_scene

    scene = Scene.read(args.scene) if args.scene else (base or default_scene)()
    if getattr(args, "velocity", None) is not None:
        scene = scene.with_ball(velocity=args.velocity)
    if args.resolution is not None:
        scene = scene.with_face(resolution=args.resolution)
    if args.ball is not None:
        scene = scene.with_ball(rigid=args.ball == "rigid")
    if args.order is not None:
        scene = scene.with_fidelity(order=args.order)
    if args.mass_scaling is not None:
        scene = scene.with_fidelity(mass_scaling=args.mass_scaling)
    if getattr(args, "integrator", None) is not None:
        scene = scene.with_fidelity(integrator=args.integrator)
    if args.duration is not None:
        scene = replace(scene, duration=args.duration)
    return scene


def _cmd_impact_simulate(args) -> int:
    from toolkit.impact.simulate import simulate

    result = simulate(_impact_scene(args), out=args.out, progress=True, preview=not args.no_preview)
    s = result.summary()
    print(f"{s['face_nodes']} face nodes ({s['element']}), {s['ball']} ball at {s['velocity_mm_s']} mm/s: "
          f"{s['steps']} steps of {s['dt_s']:.3g} s in {s['wall_time_s']:.1f} s; max displacement "
          f"{s['max_displacement_mm']:.2f} mm, max von Mises {s['max_von_mises_mpa']:.4f} MPa, energy error "
          f"{s['energy_error']:.2%}")
    print(f"wrote {args.out}/ (face.xdmf, {'ball.xdmf, ' if result.ball is not None else ''}history.h5, "
          f"summary.json{'' if args.no_preview else ', preview.png'})")
    return 0


def _cmd_impact_dataset(args) -> int:
    from toolkit.impact.dataset import SEED_VELOCITIES, build_database
    from toolkit.impact.scene import yielding_scene

    scene = _impact_scene(args, base=yielding_scene)
    velocities = args.velocities or list(SEED_VELOCITIES)
    with _dask_client(args.dask, args.workers) as client:
        report = build_database(args.out, velocities, args.held_out, scene, workers=args.workers, executor=client,
                                retry_failed=args.retry_failed, progress=True)
    from toolkit.common.database import read_index

    print(f"{len(report.done)} simulated, {len(report.skipped)} already there or failed before, "
          f"{len(report.failed)} failed now ({report.seconds:.1f} s) -> {args.out}")
    for key, reason in report.failed.items():
        print(f"  failed {key}: {reason}")
    table = read_index(args.out)
    if len(table):
        cols = ["key", "held_out", "max_displacement_mm", "max_von_mises_mpa", "max_equivalent_plastic_strain",
                "plastic_volume_fraction", "energy_error", "wall_time_s"]
        print(table[[c for c in cols if c in table]].sort_values("key").to_string(index=False, float_format="%.4g"))
    return 1 if report.failed else 0


def _cmd_impact_train(args) -> int:
    _torch_threads(args)
    from toolkit.impact.surrogate import CONFIGS, train_surrogate

    cfg = CONFIGS[args.config]
    if args.epochs is not None:
        cfg = cfg.with_(epochs=args.epochs)
    if args.max_minutes is not None:
        cfg = cfg.with_(max_seconds=60.0 * args.max_minutes)
    model = train_surrogate(args.data, cfg, args.split, out=args.out, seed=args.seed, device=args.device,
                            resume=args.resume, progress=True)
    e = model.bundle.extra
    print(f"{cfg.name} ({cfg.network}, hidden {cfg.hidden}, layers {cfg.layers}) on the {args.split} split: "
          f"{e['epochs_run']} epochs ({e['stopped']}), best validation loss {e['best_val_loss']:.4g} at epoch "
          f"{e['best_epoch']}, {e['train_seconds']:.1f} s -> {args.out}/ (model.pt, config.json)")
    return 0


def _cmd_impact_evaluate(args) -> int:
    _torch_threads(args)
    from toolkit.impact.dataset import load_database
    from toolkit.impact.evaluation import evaluate_surrogate, write_evaluation
    from toolkit.impact.surrogate import ImpactSurrogate

    model = ImpactSurrogate.load(args.model)
    db = load_database(args.data)
    ev = evaluate_surrogate(model, db, args.split)
    write_evaluation(ev, db, model, args.out, nodes=args.nodes, frames=args.frames)
    m = ev.metrics
    print(f"{m['config']} on the {m['split']} split ({m['n_test_items']} test node series, velocities "
          f"{m['test_velocities_mm_s']} mm/s):")
    print(f"  displacement RMSE {m['displacement_rmse_mm']:.3g} mm, Pearson {m['displacement_pearson']:.4f}, "
          f"NRMSE {m['displacement_nrmse']:.3%}")
    print(f"  von Mises    RMSE {m['von_mises_rmse_mpa']:.3g} MPa, Pearson {m['von_mises_pearson']:.4f}, "
          f"NRMSE {m['von_mises_nrmse']:.3%}")
    print(f"  trained {m['train_seconds']:.1f} s; {m['inference_ms']:.2f} ms per whole-face frame "
          f"(FE {m['fe_ms_per_frame']:.0f} ms per frame)")
    print(f"wrote {args.out}/ (metrics.json, timeseries.png, fields.png)")
    return 0


def _cmd_impact_predict(args) -> int:
    _torch_threads(args)
    from toolkit.impact.surrogate import ImpactSurrogate, predict_scene

    pred = predict_scene(ImpactSurrogate.load(args.model), args.velocity)
    pred.write(args.out)
    s = pred.summary()
    print(f"{s['face_nodes']} face nodes at {s['velocity_mm_s']} mm/s, {pred.times.size} frames in "
          f"{s['wall_time_s']:.2f} s: max displacement {s['max_displacement_mm']:.2f} mm, max von Mises "
          f"{s['max_von_mises_mpa']:.4f} MPa")
    print(f"wrote {args.out}/ (face.xdmf, summary.json, scene.toml)")
    return 0


def _cmd_static_simulate(args) -> int:
    result = _run_static(args.mesh, args.resolution, args.plan, args.increments, args.material, args.sliding,
                         args.solver, args.force, progress=True, bones=_bones(args.bone))
    result.write(args.out, preview=not args.no_preview)
    s = result.summary()
    for r in s["increments_report"]:
        print(f"increment {r['increment']}: {r['seconds_step1'] + r['seconds_step2']:.1f} s, {r['linear_solves']} "
              f"linear solves, {r['substeps']} sub-step(s), min scaled Jacobian {r['min_scaled_jacobian']:.3f}")
    print(f"{s['nodes']} nodes, {s['increments']} increments, {s['material']}, {s['sliding']}: "
          f"max displacement {s['max_displacement_mm']:.2f} mm, min scaled Jacobian {s['min_scaled_jacobian']:.3f}, "
          f"max penetration {s['max_penetration_mm']:.2e} mm, {s['wall_time_s']:.1f} s")
    print(f"wrote {args.out}/ (result.vtu: pre-operative face with 'displacement'; postop.vtu: post-operative face; "
          f"increments.xdmf, summary.json{'' if args.no_preview else ', preview.png'})")
    return 0


def _add_database_run(parser: argparse.ArgumentParser, items: str) -> None:
    """Where a learning database's simulations run and where it is written (both workflows)."""
    parser.add_argument("--workers", type=int, default=1, help="local worker processes (default 1; 0: in this process)")
    parser.add_argument("--dask", "--scheduler", dest="dask", metavar="ADDRESS", default=None,
                        help="run on a Dask cluster: a scheduler address (tcp://host:8786) or 'local' for a "
                             "LocalCluster of --workers processes")
    parser.add_argument("--retry-failed", action="store_true", help=f"rerun {items} recorded as failed")
    parser.add_argument("--out", required=True, type=Path, help="database file (.h5)")


@contextmanager
def _dask_client(address: str | None, workers: int):
    """A Dask client for ``--dask`` (a scheduler address, or ``local``: a LocalCluster of
    ``workers`` single-threaded processes); None without it. Closed on exit."""
    if not address:
        yield None
        return
    from distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=max(workers, 1), threads_per_worker=1, dashboard_address=None) \
        if address == "local" else None
    client = None
    try:
        client = Client(cluster if cluster is not None else address)
        yield client
    finally:
        if client is not None:
            client.close()
        if cluster is not None:
            cluster.close()


def _cmd_static_dataset(args) -> int:
    from toolkit.static.dataset import DatasetConfig, generate

    config = DatasetConfig(resolution=args.resolution, subjects=args.subjects, plans=args.plans, mode=args.mode,
                           increments=args.increments, material=args.material, sliding=args.sliding, seed=args.seed,
                           poisson_range=tuple(args.poisson_range) if args.poisson_range else None)
    with _dask_client(args.dask, args.workers) as client:
        report = generate(args.out, config, executor=client, workers=args.workers, retry_failed=args.retry_failed)
    print(f"{len(report.done)} simulations done, {len(report.skipped)} already there, {len(report.failed)} failed "
          f"in {report.seconds:.1f} s -> {args.out}")
    for key, reason in list(report.failed.items())[:10]:
        print(f"  failed {key}: {reason[:160]}")
    return 0


def _cmd_static_train(args) -> int:
    from toolkit.static.features import FeatureSpec
    from toolkit.static.surrogate import SurrogateConfig, train_surrogate

    config = SurrogateConfig(
        FeatureSpec(args.variant, args.extra_channels, args.material_channels, args.linear_prior),
        network=args.network,
        coarse_radii=_database_resolution(args.data) == "coarse",
        split="subjects" if args.test_subjects else "plans", test_subjects=tuple(args.test_subjects or ()),
        epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed, device=args.device,
        max_seconds=None if args.max_minutes is None else 60 * args.max_minutes, lr_schedule=args.lr_schedule)
    model = train_surrogate(args.data, args.out, config, resume=args.resume)
    x = model.bundle.extra
    print(f"trained {config.features.variant} PointNet++ ({x['parameters']:,} parameters) on {x['split']['train']} "
          f"samples in {x['train_seconds']:.0f} s: best epoch {x['best_epoch']} ({x['stopped']}) -> {args.out}")
    return 0


def _database_resolution(path) -> str:
    import json as _json

    from toolkit.common.database import Database

    return _json.loads(Database.open_attrs(Path(path)).get("config", "{}")).get("resolution", "paper")


def _cmd_static_evaluate(args) -> int:
    from toolkit.static.dataset import subject_phantom
    from toolkit.static.surrogate import Surrogate, evaluate_surrogate, write_evaluation

    model = Surrogate.load(args.model, device=args.device)
    result = evaluate_surrogate(model, args.data)
    mesh = None if args.no_render else subject_phantom(_database_resolution(args.data), 0).mesh
    write_evaluation(result, args.out, mesh)
    m = result["metrics"]
    print(f"{m['samples']} samples: mean error {m['mean_error_mm']:.3f} mm (median {m['median_error_mm']:.3f}, p95 "
          f"{m['p95_error_mm']:.3f}, max {m['max_error_mm']:.3f}); free nodes {m['free_mean_error_mm']:.3f}, lips "
          f"{m['lips_mean_error_mm']:.3f}; {m['inference_ms']:.1f} ms per prediction vs {m['fe_ms']:.0f} ms FE per "
          f"increment -> {args.out}/metrics.json")
    return 0


def _cmd_static_predict(args) -> int:
    from toolkit.common.io import read
    from toolkit.static import SurgicalPlan, default_plan
    from toolkit.static.bones import segments_from_files
    from toolkit.static.boundary import BoundaryError, segments_from_mesh
    from toolkit.static.dataset import subject_phantom
    from toolkit.static.surrogate import Surrogate

    model = Surrogate.load(args.model, device=args.device)
    bones = _bones(args.bone)
    if args.mesh is None:
        phantom = subject_phantom(args.resolution or model.bundle.data["database"]["resolution"], 0)
        plan = SurgicalPlan.read(args.plan, phantom=phantom) if args.plan else default_plan(phantom)
        segments = dict(phantom.segments)
        segments.update(segments_from_files(phantom.mesh, bones, {k: s.pivot for k, s in phantom.segments.items()}))
        result = model.predict_plan(phantom, plan, segments=segments)
    else:
        if args.plan is None:
            raise ValueError("--mesh needs --plan (with pivot_mm for every rotating segment)")
        mesh = read(args.mesh, require_node_sets=["fixed"])
        plan = SurgicalPlan.read(args.plan)
        pivots = {k: m.pivot for k, m in plan.motions.items()}
        try:
            segments = segments_from_mesh(mesh, pivots)
        except BoundaryError:
            if not bones:
                raise
            segments = {}
        segments.update(segments_from_files(mesh, bones, pivots))
        result = model.predict_plan(mesh, plan, segments=segments)
    result.write(args.out, preview=not args.no_preview)
    s = result.summary()
    print(f"{s['nodes']} nodes, {s['increments']} increments predicted in {s['wall_time_s'] * 1e3:.0f} ms: max "
          f"displacement {s['max_displacement_mm']:.2f} mm, min scaled Jacobian {s['min_scaled_jacobian']:.3f} -> "
          f"{args.out}/ (result.vtu, postop.vtu, increments.xdmf, summary.json)")
    return 0


def _bones(specs: list[str]) -> dict:
    """``["lefort=maxilla.stl", ...]`` -> ``{"lefort": Path("maxilla.stl"), ...}``."""
    out = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--bone {spec!r}: expected SEGMENT=FILE, e.g. --bone lefort=maxilla.stl")
        if name in out:
            raise ValueError(f"--bone {name}= given twice")
        out[name] = Path(path)
    return out


def _run_static(mesh_path, resolution, plan_path, increments, material, sliding, solver="auto", force=False,
                progress=False, bones=None):
    from toolkit.common.io import read
    from toolkit.common.phantom import face_hex
    from toolkit.static import SimulationOptions, SurgicalPlan, default_plan, simulate
    from toolkit.static.bones import segments_from_files
    from toolkit.static.boundary import BoundaryError, segments_from_mesh

    options = SimulationOptions(solver=solver, progress=progress)
    bones = bones or {}
    if mesh_path is None:
        phantom = face_hex(resolution)
        plan = SurgicalPlan.read(plan_path, phantom=phantom) if plan_path else default_plan(phantom, force=force)
        if force and plan_path:
            plan = SurgicalPlan(plan.motions, force=True)
        segments = dict(phantom.segments)
        segments.update(segments_from_files(phantom.mesh, bones, {k: s.pivot for k, s in phantom.segments.items()}))
        return simulate(phantom, plan, increments, material, sliding, segments=segments, options=options)
    mesh = read(mesh_path, require_node_sets=["fixed"])
    if plan_path is None:
        raise ValueError("--mesh needs --plan (with pivot_mm for every rotating segment)")
    plan = SurgicalPlan.read(plan_path)
    if force:
        plan = SurgicalPlan(plan.motions, force=True)
    pivots = {k: m.pivot for k, m in plan.motions.items()}
    try:
        segments = segments_from_mesh(mesh, pivots)
    except BoundaryError:
        if not bones:
            raise
        segments = {}
    segments.update(segments_from_files(mesh, bones, pivots))
    return simulate(mesh, plan, increments, material, sliding, segments=segments, options=options)


def _phantom_shape(args):
    from dataclasses import replace

    from toolkit.common.phantom import FaceShape

    shape = FaceShape.sample(args.seed) if args.seed is not None else FaceShape()
    if args.mouth_open is not None:
        shape = replace(shape, mouth_open=args.mouth_open)
    return shape


def _build(kind: str, resolution: str, shape=None):
    from toolkit.common.phantom import ball, face_hex, face_tet

    if kind == "face-hex":
        return face_hex(resolution, shape).mesh
    if kind.startswith("face-tet"):
        return face_tet(resolution, order=1 if kind.endswith("4") else 2, shape=shape)
    return ball(resolution=resolution, order=1 if kind.endswith("4") else 2)


def _cmd_phantom(args) -> int:
    from toolkit.common.io import write

    mesh = _build(args.kind, args.resolution, _phantom_shape(args) if args.kind.startswith("face") else None)
    mesh.check()
    write(args.out, mesh)
    print(f"wrote {args.out}: {mesh}")
    if args.preview:
        from toolkit.common.plotting import render

        render(mesh, args.preview, title=f"{args.kind} ({args.resolution})")
        print(f"wrote {args.preview}")
    return 0


def _cmd_demo(args) -> int:
    from toolkit.common.io import write
    from toolkit.common.plotting import render

    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    t_all = time.perf_counter()
    for name, kind in (("face_hex", "face-hex"), ("face_tet10", "face-tet10"), ("ball", "ball-tet10")):
        t0 = time.perf_counter()
        mesh = _build(kind, args.resolution)
        sj = mesh.check().scaled_jacobian()
        write(out / f"{name}.inp", mesh)
        write(out / f"{name}.vtu", mesh)
        if not args.no_render:
            render(mesh, out / f"{name}.png", camera="inner" if name == "face_hex" else "iso", node_sets=_preview_sets(mesh),
                   title=f"{name} ({args.resolution}): {mesh.n_points} nodes, {mesh.n_cells} elements")
        rows.append({"mesh": name, "cell_type": mesh.volume_type, "nodes": mesh.n_points, "elements": mesh.n_cells,
                     "min_scaled_jacobian": round(float(sj.min()), 4), "node_sets": sorted(mesh.node_sets),
                     "element_sets": sorted(mesh.element_sets), "seconds": round(time.perf_counter() - t0, 2)})
    t0 = time.perf_counter()
    static = _run_static(None, args.resolution, None, 3, "linear", "mucosa+lip")
    static.write(out / "static", preview=not args.no_render)
    st = static.summary()
    st_seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    impact = _demo_impact(out / "impact", preview=not args.no_render)
    im = impact.summary()
    im_seconds = time.perf_counter() - t0
    summary = {"resolution": args.resolution, "meshes": rows, "wall_time_s": round(time.perf_counter() - t_all, 2),
               "static": {k: v for k, v in st.items() if k != "increments_report"}, "impact": im}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"{'mesh':<12}{'type':<7}{'nodes':>8}{'elements':>10}{'min SJ':>9}{'s':>7}")
    for r in rows:
        print(f"{r['mesh']:<12}{r['cell_type']:<7}{r['nodes']:>8}{r['elements']:>10}"
              f"{r['min_scaled_jacobian']:>9.3f}{r['seconds']:>7.2f}")
    print(f"static: default plan, 3 increments, mucosa+lip sliding: max displacement "
          f"{st['max_displacement_mm']:.2f} mm, max lip penetration {st['max_penetration_mm']:.1e} mm, "
          f"{st_seconds:.1f} s -> {out}/static/")
    print(f"impact: rigid ball at 30 mm/s for {impact.times[-1]:.2f} s on the coarse tet4 face (mass scaling 100): "
          f"max displacement {im['max_displacement_mm']:.1f} mm, max von Mises {im['max_von_mises_mpa']:.4f} MPa, "
          f"energy error {im['energy_error']:.2%}, {im_seconds:.1f} s -> {out}/impact/")
    print(f"wrote {out}/ (.inp, .vtu, .png, static/, impact/, summary.json) in {summary['wall_time_s']:.1f} s")
    return 0


def _demo_impact(out, preview=True):
    """A short coarse impact: the fastest fidelity options (see benchmarks/impact_ladder.py)."""
    from dataclasses import replace

    from toolkit.impact import default_scene, simulate

    scene = default_scene().with_face(resolution="coarse").with_ball(rigid=True)
    scene = replace(scene.with_fidelity(order=1, mass_scaling=100.0), duration=0.9, n_frames=9)
    return simulate(scene, out=out, preview=preview)


def _preview_sets(mesh) -> dict:
    """The boundary node sets of a phantom (or the ball's surface), for previews."""
    from toolkit.common.phantom import BOUNDARY_SETS

    names = [n for n in BOUNDARY_SETS if n in mesh.node_sets] or [n for n in ("fixed", "surface") if n in mesh.node_sets]
    return {n: mesh.node_sets[n] for n in names}


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s")
    from toolkit.common.runtime import set_threads

    set_threads(args.threads)
    try:
        return int(args.func(args) or 0)
    except KeyboardInterrupt:
        print("interrupted; finished files are complete (all writes are atomic)", file=sys.stderr)
        return 130
    except (ValueError, KeyError, FileNotFoundError, RuntimeError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
