"""``toolkit impact ...``: the ball-impact workflow (the impact paper) and its LSTM surrogate."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from toolkit.cli._common import (
    EPOCHS_KEPT,
    NOTHING_WRITTEN,
    SIMULATIONS_KEPT,
    Command,
    add_axes,
    add_database_run,
    add_units,
    dask_client,
    floats,
    ints,
    positive_float,
    positive_int,
    probability,
    tolerance_mm,
    torch_threads,
    uninterruptible,
)

HELP = "ball-impact workflow (the impact paper)"
DESCRIPTION = ("Impact workflow: elastoplastic simulation of a ball pressed into the face (quasi-static load steps "
               "by default, explicit dynamics by name), its database and surrogate.")

CONFIG_NAMES = ["paper", "strong", "baseline"]


def _add_scene_options(parser: argparse.ArgumentParser, scene: str) -> None:
    """Options that change the scene (each one keeps the scene's own value when not given)."""
    parser.add_argument("--scene", type=Path, help=f"scene TOML (default: {scene})")
    parser.add_argument("--resolution", choices=["coarse", "paper"], help="face resolution (default: the scene's)")
    parser.add_argument("--mesh", type=Path,
                        help="face mesh (.vtu/.inp/.xdmf, tet4 or tet10) with node sets fixed and skin (and bone for "
                             "--support skull), as `toolkit mesh` writes it (default: the phantom at --resolution)")
    add_units(parser)
    add_axes(parser, "the --mesh file (--target is in the toolkit's axes)")
    parser.add_argument("--target", type=_point, metavar="X,Y,Z",
                        help="skin point (mm) the ball's centre line passes through (default: the scene's aim, 30 mm "
                             "above the most anterior skin point)")
    parser.add_argument("--support", choices=["band", "skull"],
                        help="how the face is held: its fixed set only (band; for a `toolkit mesh` face, the "
                             "truncation cuts) or the bone-side surface too (skull) (default: the scene's; with "
                             "--mesh, skull: the tissue on the bones holds the face, the truncation cuts are free)")
    parser.add_argument("--ball", choices=["deformable", "rigid"], help="ball model (default: the scene's)")
    parser.add_argument("--order", type=int, choices=[1, 2],
                        help="tetrahedron order (1: tet4, 2: tet10) (default: the scene's; with --mesh, the mesh's, "
                             "and another order is refused)")
    parser.add_argument("--mass-scaling", type=float,
                        help="explicit integrator (with --integrator explicit): density factor >= 1 (longer stable "
                             "steps) (default: the scene's, 1)")
    parser.add_argument("--safety", type=float,
                        help="explicit integrator (with --integrator explicit): time-step safety factor in (0, 1] "
                             "on the critical step (default: the scene's, 0.9)")


def add_simulate_arguments(parser: argparse.ArgumentParser) -> None:
    _add_scene_options(parser, "the impact paper's scene: paper face, deformable ball, tet10, no mass scaling")
    parser.add_argument("--velocity", type=float,
                        help="ball velocity, mm/s (the impact paper: 20-50) (default: the scene's, 30)")
    parser.add_argument("--integrator", choices=["quasi-static", "explicit"],
                        help="quasi-static Newton load steps (the same answer as explicit dynamics at these ball "
                             "speeds, in a fraction of the time) or explicit dynamics (the impact paper) (default: "
                             "the scene's, quasi-static; with --tolerance, chosen)")
    parser.add_argument("--duration", type=float,
                        help="simulated time, s (default: the scene's, 1.8; with --mesh, 0.36)")
    parser.add_argument("--tolerance", type=tolerance_mm, default=None, metavar="MM",
                        help="choose the ball, order, mass scaling, safety and integrator not given: the fastest "
                             "measured in the impact ladder (coarse face, 30 mm/s) whose error (mm, 95th percentile "
                             "of the nodal difference to the explicit reference over nodes and frames) is within MM; "
                             "refused below the reference's own uncertainty, its left-right asymmetry (default: "
                             "none, the options above)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--no-preview", action="store_true", help="skip preview.png")


def simulate(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir
    from toolkit.impact.scene import default_scene
    from toolkit.impact.simulate import simulate

    check_output_dir(args.out)
    run_scene = scene(args, default_scene)
    choice = None
    if args.tolerance is not None:
        choice = choose_impact_fidelity(args, run_scene)
        run_scene = run_scene.with_fidelity_choice(choice)
    result = simulate(run_scene, out=args.out, progress=True, preview=not args.no_preview, fidelity=choice)
    s = result.summary()
    print(f"{s['face_nodes']} face nodes ({s['element']}), {s['ball']} ball at {s['velocity_mm_s']} mm/s: "
          f"{s['steps']} steps of {s['dt_s']:.3g} s in {s['wall_time_s']:.1f} s; max displacement "
          f"{s['max_displacement_mm']:.2f} mm, max von Mises {s['max_von_mises_mpa']:.4f} MPa, energy error "
          f"{s['energy_error']:.2%}")
    print(f"wrote {args.out}/ (face.xdmf, {'ball.xdmf, ' if result.ball is not None else ''}history.h5, "
          f"summary.json, scene.toml{'' if args.no_preview else ', preview.png'})")
    return 0


def add_database_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--velocities", type=floats, default=None,
                        help="training velocities, mm/s, comma-separated (default: the impact paper's "
                             "20,26,32,38,44,50)")
    parser.add_argument("--held-out", type=floats, default=None,
                        help="held-out velocities, mm/s (default: midpoints of every other gap, 23,35,47); '' for "
                             "none")
    _add_scene_options(parser, "the skull-held yielding scene, 0.36 s")
    parser.add_argument("--integrator", choices=["quasi-static", "explicit"],
                        help="quasi-static load steps (the FE that answers `toolkit impact predict --tolerance` "
                             "when the surrogate may miss) or explicit dynamics (the impact paper) (default: the "
                             "scene's, quasi-static)")
    parser.add_argument("--duration", type=float, help="simulated time, s (default: the scene's, 0.36)")
    add_database_run(parser, "velocities")


def database(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_file
    from toolkit.common.papers import BALL_VELOCITIES
    from toolkit.common.training.database import read_index
    from toolkit.impact.database import build_database
    from toolkit.impact.scene import yielding_scene

    check_output_file(args.out, what="database file")
    velocities = list(BALL_VELOCITIES) if args.velocities is None else args.velocities
    if not velocities:
        raise ValueError("--velocities gives no velocity; expected comma-separated mm/s, e.g. --velocities 20,35,50 "
                         "(or leave it out for the impact paper's)")
    with dask_client(args.dask, args.workers) as client:
        report = build_database(args.out, velocities, args.held_out, scene(args, yielding_scene), workers=args.workers,
                                executor=client, retry_failed=args.retry_failed, progress=True)
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


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="database (.h5) from `toolkit impact database`")
    parser.add_argument("--out", required=True, type=Path, help="model directory")
    parser.add_argument("--config", default="strong", choices=CONFIG_NAMES,
                        help="a stronger LSTM (strong, the best measured), the impact paper's per-output LSTM "
                             "(paper) or the non-recurrent baseline (baseline)")
    parser.add_argument("--split", default="random", choices=["random", "velocity"],
                        help="random: 76%% of the items train (the impact paper); velocity: held-out velocities are "
                             "the test set")
    parser.add_argument("--device", default="cpu", help="cpu, cuda, cuda:N or auto")
    parser.add_argument("--seed", type=int, default=0, help="weights, batch order and split")
    parser.add_argument("--epochs", type=positive_int, default=None,
                        help="maximum epochs (default: the configuration's)")
    parser.add_argument("--max-minutes", type=positive_float, default=None,
                        help="training time limit (default: the configuration's, 15)")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")


def train(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_model_dir

    check_model_dir(args.out, resume=args.resume)
    torch_threads(args)
    from toolkit.impact.surrogate import resolve_config, train_surrogate

    cfg = resolve_config(args.config)
    if args.epochs is not None:
        cfg = cfg.with_(epochs=args.epochs)
    if args.max_minutes is not None:
        cfg = cfg.with_(max_seconds=60.0 * args.max_minutes)
    model = train_surrogate(args.data, cfg, args.split, out=args.out, seed=args.seed, device=args.device,
                            resume=args.resume, progress=True)
    e = model.bundle.extra
    print(f"{cfg.name} ({cfg.network}, hidden {cfg.hidden}, layers {cfg.layers}) on the {args.split} split: "
          f"{e['epochs_run']} epochs ({e['stop_reason']}), best validation loss {e['best_val_loss']:.4g} at epoch "
          f"{e['best_epoch']}, {e['train_seconds']:.1f} s -> {args.out}/ (model.pt, config.json)")
    return 0


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory")
    parser.add_argument("--data", required=True, type=Path, help="the database it was trained on")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--split", choices=["random", "velocity"], default=None,
                        help="test split (default: the one the model was trained with)")
    parser.add_argument("--nodes", type=ints, default=None,
                        help="node ids for timeseries.png, comma-separated (default: the test nodes of largest final "
                             "displacement, largest stress and median displacement)")
    parser.add_argument("--frames", type=ints, default=None,
                        help="frame indices for fields.png, comma-separated (default: the middle and the last)")


def evaluate(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir

    check_output_dir(args.out)
    torch_threads(args)
    from toolkit.impact.database import load_database
    from toolkit.impact.evaluation import check_figure_choices, evaluate_surrogate, write_evaluation
    from toolkit.impact.surrogate import Surrogate

    model = Surrogate.load(args.model)
    db = load_database(args.data)
    model.check_database(db)
    check_figure_choices(db, args.nodes, args.frames)
    ev = evaluate_surrogate(model, db, split=args.split)
    with uninterruptible():
        write_evaluation(ev, db, model, args.out, nodes=args.nodes, frames=args.frames)
    m = ev.metrics
    print(f"{m['config']} on the {m['split']} split ({m['n_test_items']} test node series, velocities "
          f"{m['test_velocities_mm_s']} mm/s):")
    print(f"  displacement RMSE {m['displacement_rmse_mm']:.3g} mm, Pearson {m['displacement_pearson']:.4f}, "
          f"NRMSE {m['displacement_nrmse']:.4f} of the peak (metrics.json: displacement_nrmse)")
    print(f"  von Mises    RMSE {m['von_mises_rmse_mpa']:.3g} MPa, Pearson {m['von_mises_pearson']:.4f}, "
          f"NRMSE {m['von_mises_nrmse']:.4f} of the peak (von_mises_nrmse)")
    print(f"  trained {m['train_seconds']:.1f} s; {m['inference_ms']:.2f} ms per whole-face frame "
          f"(FE {m['fe_ms_per_frame']:.0f} ms per frame)")
    print(f"wrote {args.out}/ (metrics.json, timeseries.png, fields.png)")
    return 0


def add_predict_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory")
    parser.add_argument("--velocity", required=True, type=float, help="ball velocity, mm/s")
    parser.add_argument("--tolerance", type=tolerance_mm, default=None, metavar="MM",
                        help="answer within this error (mm, 95th percentile of the nodal error over nodes and "
                             "frames): the surrogate's prediction when its calibrated estimate is within it and the "
                             "scene is like its training data, else the quasi-static FE of the same scene (needs "
                             "`toolkit impact calibrate`)")
    parser.add_argument("--coverage", type=probability, default=None,
                        help="with --tolerance: the estimate's coverage (default: the calibration's)")
    parser.add_argument("--target", type=_point, metavar="X,Y,Z", default=None,
                        help="with --tolerance: skin point (mm) the ball aims at (default: the training scene's aim; "
                             "another aim is answered by the FE)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--no-preview", action="store_true", help="skip preview.png")


def predict(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir

    check_output_dir(args.out)
    torch_threads(args)
    from toolkit.impact.surrogate import Surrogate, predict_scene

    if args.tolerance is None:
        if args.coverage is not None or args.target is not None:
            raise ValueError("--coverage and --target go with --tolerance (an answer within a tolerance)")
    else:
        return _predict_within(args)
    pred = predict_scene(Surrogate.load(args.model), args.velocity)
    with uninterruptible():
        pred.write(args.out, preview=not args.no_preview)
    s = pred.summary()
    print(f"{s['face_nodes']} face nodes at {s['velocity_mm_s']} mm/s, {pred.times.size} frames in "
          f"{s['wall_time_s']:.2f} s: max displacement {s['max_displacement_mm']:.2f} mm, max von Mises "
          f"{s['max_von_mises_mpa']:.4f} MPa")
    from toolkit.common.training import describe_extrapolation

    print(f"velocity: {describe_extrapolation(s['extrapolation'])}")
    print(f"wrote {args.out}/ (face.xdmf, summary.json, scene.toml)")
    checks = s["checks"]["answer"]
    if not checks["passed"]:
        print(f"warning: the answer failed its checks ({'; '.join(checks['problems'])}); summary.json flags it "
              "(checks.answer.passed false). Rerun with --tolerance MM to have the FE answer instead, or run it "
              f"with `toolkit impact simulate --scene {args.out}/scene.toml`", file=sys.stderr)
    return 0


def _predict_within(args: argparse.Namespace) -> int:
    from toolkit.impact.scene import Scene
    from toolkit.impact.surrogate import Surrogate
    from toolkit.impact.trust import Calibration, answer

    model = Surrogate.load(args.model)
    calibration = Calibration.load(args.model)
    if args.coverage is not None:
        calibration = calibration.at(args.coverage)
    scene = Scene.from_dict(model.bundle.data["scene"]).with_ball(velocity=args.velocity)
    if args.target is not None:
        scene = scene.with_ball(target=args.target, target_offset=(0.0, 0.0, 0.0))
    result = answer(model, None, args.tolerance, scene=scene, calibration=calibration, out=args.out, progress=True,
                    preview=not args.no_preview)
    s = result.summary()
    a, sec = s["answer"], result.seconds
    print(f"answered by {'the surrogate' if a['answered_by'] == 'surrogate' else 'the quasi-static FE'}: "
          f"{a['reason']}")
    print(f"{s['face_nodes']} face nodes at {s['velocity_mm_s']} mm/s: max displacement "
          f"{s['max_displacement_mm']:.2f} mm; surrogate {sec['surrogate']:.2f} s, estimate {sec['estimate']:.2f} s, "
          f"FE {sec['fe']:.1f} s -> {args.out}/ (face.xdmf, summary.json)")
    return 0


#: the scales of :data:`toolkit.impact.trust.SCALES` (named here so that building the parser imports
#: no numerical library; a test keeps the two equal)
IMPACT_SCALES = ("interpolation", "constant")


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory (the calibration is saved in it)")
    parser.add_argument("--data", required=True, type=Path,
                        help="a database of the model's scene: its simulations at velocities the model did not "
                             "train on are the calibration cases")
    parser.add_argument("--train-data", type=Path, default=None,
                        help="the database the model was trained on, when --data is another one (default: --data)")
    parser.add_argument("--coverage", type=probability, default=0.9,
                        help="probability that the error bound holds for a velocity like these")
    parser.add_argument("--scale", choices=IMPACT_SCALES, default=IMPACT_SCALES[0],
                        help="interpolation: the distance to the training simulations interpolated in velocity; "
                             "constant: one bound for all")


def calibrate(args: argparse.Namespace) -> int:
    torch_threads(args)
    from toolkit.impact.surrogate import Surrogate
    from toolkit.impact.trust import calibrate_surrogate

    model = Surrogate.load(args.model)
    cal = calibrate_surrogate(model, args.data, coverage=args.coverage, scale=args.scale, training=args.train_data)
    with uninterruptible():
        cal.save(args.model)
    errors = sorted(c["error_mm"] for c in cal.cases)
    print(f"{cal.bound.n} velocities the model did not train on: answer error (p95 over nodes and frames) median "
          f"{errors[len(errors) // 2]:.3f} mm, max {errors[-1]:.3f} mm; {args.scale} scale x {cal.bound.factor:.3g} "
          f"bounds it at {cal.bound.coverage:.0%} -> {args.model}/calibration.json")
    return 0


def choose_impact_fidelity(args: argparse.Namespace, run_scene):
    """The FidelityChoice of ``--tolerance`` (printed): among the ladder's options with those given
    on the command line; on a face mesh, with the mesh's element order."""
    from toolkit.common.fidelity import choose_fidelity

    given = {"ball": args.ball, "order": args.order, "mass_scaling": args.mass_scaling, "safety": args.safety,
             "integrator": args.integrator}
    fixed = {k: v for k, v in given.items() if v is not None}
    own_mesh = run_scene.face.mesh is not None
    if own_mesh:
        fixed.setdefault("order", run_scene.fidelity.order)
    choice = choose_fidelity("impact", args.tolerance, fixed=fixed, own_mesh=own_mesh)
    print(choice.describe())
    return choice


def _point(text: str) -> tuple[float, float, float]:
    """``"0,-80,10"`` -> ``(0.0, -80.0, 10.0)`` mm (an argparse type)."""
    values = floats(text)
    if len(values) != 3:
        raise argparse.ArgumentTypeError(f"expected a point X,Y,Z in mm, got {text!r}")
    return tuple(values)


def scene(args: argparse.Namespace, base):
    """The scene of ``--scene`` (or ``base()``) with the options given on the command line."""
    from dataclasses import replace

    from toolkit.impact.scene import Scene

    if args.mesh is not None and args.resolution is not None:
        raise ValueError(f"--mesh {args.mesh} and --resolution {args.resolution} both choose the face; give one")
    if args.mesh is None and args.axes != "toolkit":
        raise ValueError(f"--axes {args.axes} applies to a --mesh file; give --mesh FACE.vtu, or leave it out")
    if args.scene:
        out = Scene.read(args.scene)
        out = out if args.mesh is None else out.with_face(mesh=str(args.mesh), units=args.units, axes=args.axes)
    elif args.mesh is not None:
        from toolkit.impact.scene import meshed_scene

        out = meshed_scene(args.mesh, args.units, axes=args.axes)
        if args.support == "band":  # held by its own fixed set (the truncation cuts), not by the bones
            out = out.with_face(fixed_set="fixed")
    else:
        out = base()
    if getattr(args, "velocity", None) is not None:
        out = out.with_ball(velocity=args.velocity)
    if args.resolution is not None:
        out = out.with_face(resolution=args.resolution)
    if args.target is not None:
        out = out.with_ball(target=args.target, target_offset=(0.0, 0.0, 0.0))
    if args.support is not None:
        out = out.with_face(support=args.support)
    if args.ball is not None:
        out = out.with_ball(rigid=args.ball == "rigid")
    if args.order is not None:
        out = out.with_fidelity(order=args.order)
    integrator = getattr(args, "integrator", None) or out.fidelity.integrator
    explicit = {k: v for k, v in (("mass_scaling", args.mass_scaling), ("safety", args.safety)) if v is not None}
    if explicit and integrator != "explicit":
        given = " and ".join(f"--{k.replace('_', '-')} {v:g}" for k, v in explicit.items())
        verb, them = ("apply", "them") if len(explicit) > 1 else ("applies", "it")
        raise ValueError(f"{given} {verb} to the explicit integrator only (the {integrator} one has no inertia "
                         f"and no time step): add --integrator explicit, or leave {them} out")
    out = out.with_fidelity(integrator=integrator, **explicit)
    if args.duration is not None:
        out = replace(out, duration=args.duration)
    return out


COMMANDS = {
    "simulate": Command(
        help="run an impact scene",
        description="Run the simulation (quasi-static by default, or explicit) and write face.xdmf (displacement, "
                    "von_mises), ball.xdmf (deformable ball), history.h5, summary.json, scene.toml and preview.png.",
        add_arguments=add_simulate_arguments, run=simulate,
        interrupted="{out} holds nothing from this run, or summary.json with \"status\": \"interrupted\" and the "
                    "frames finished so far (readable); rerun the same command to run it whole"),
    "database": Command(
        help="build the learning database (one simulation per velocity)",
        description="Simulate the scene at every training and held-out velocity and store the per-node "
                    "displacement and von Mises time series in one resumable HDF5 file (rerun to resume; failures "
                    "are recorded). Default scene: the face held by the skull, 0.36 s (yielding_scene).",
        add_arguments=add_database_arguments, run=database, interrupted=SIMULATIONS_KEPT),
    "train": Command(
        help="train a surrogate on a database",
        description="Train the impact paper's LSTM, the stronger LSTM or the non-recurrent baseline; writes "
                    "model.pt, weights.npz, config.json (with the scalers) and checkpoint.pt.",
        add_arguments=add_train_arguments, run=train, interrupted=EPOCHS_KEPT),
    "evaluate": Command(
        help="score a model on its test split",
        description="RMSE, Pearson and NRMSE of displacement and von Mises on the model's test split; writes "
                    "metrics.json, timeseries.png and fields.png.",
        add_arguments=add_evaluate_arguments, run=evaluate, interrupted=NOTHING_WRITTEN),
    "calibrate": Command(
        help="calibrate a model's error estimate",
        description="Predict the simulations of a database at velocities the model did not train on, compare with "
                    "their FE and save the split-conformal error bound in the model directory (calibration.json, "
                    "calibration.npz), which `toolkit impact predict --tolerance` uses.",
        add_arguments=add_calibrate_arguments, run=calibrate, interrupted=NOTHING_WRITTEN),
    "predict": Command(
        help="predict the database's scene at a velocity",
        description="Whole-face displacement and von Mises time series at VELOCITY; writes face.xdmf, summary.json "
                    "and scene.toml (run its FE with `toolkit impact simulate --scene OUT/scene.toml`). With "
                    "--tolerance, the surrogate answers when its calibrated error estimate is within it and the "
                    "scene is like its training data, and the quasi-static FE answers otherwise; summary.json says "
                    "which (answer.answered_by) and why.",
        add_arguments=add_predict_arguments, run=predict,
        interrupted="{out} holds nothing from this run, or (the FE answering with --tolerance) summary.json with "
                    "\"status\": \"interrupted\" and the frames finished so far; rerun the same command"),
}
