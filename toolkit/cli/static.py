"""``toolkit static ...``: the orthognathic-surgery workflow (the lip-sliding paper) and its
PointNet++ surrogate (the PointNet++ paper)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from toolkit.cli._common import (
    EPOCHS_KEPT,
    NOTHING_WRITTEN,
    RESOLUTIONS,
    SIMULATIONS_KEPT,
    Command,
    add_axes,
    add_database_run,
    add_units,
    dask_client,
    positive_float,
    positive_int,
    probability,
    tolerance_mm,
    two_points,
    uninterruptible,
)
from toolkit.common.defaults import STATIC_SIMULATION

HELP = "orthognathic-surgery workflow (the lip-sliding paper)"
DESCRIPTION = "Static workflow: incremental FEM of the face after orthognathic surgery."
MATERIALS = ["linear", "neo-hookean"]
SLIDINGS = ["none", "mucosa", "mucosa+lip"]
#: simulate's fidelity options when neither given nor chosen by --tolerance (those of Python)
SIMULATE_DEFAULTS = dict(STATIC_SIMULATION)


def add_simulate_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--mesh", type=Path,
                        help="face mesh (.inp/.vtu/.xdmf) with the phantom's node sets (default: the built-in phantom)")
    source.add_argument("--resolution", default=None, choices=RESOLUTIONS,
                        help="built-in phantom resolution (default: coarse; with --tolerance, chosen)")
    parser.add_argument("--plan", type=Path,
                        help="plan (.toml/.json) (default: the packaged bimaxillary plan, phantom only)")
    parser.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE",
                        help="bone surface of a segment (lefort, distal, proximal_left, proximal_right, skull) as "
                             "STL/OBJ/PLY/VTK/VTU/OFF in mm, e.g. --bone lefort=maxilla.stl; repeatable (default: "
                             "the phantom's surfaces, or for --mesh the surfaces rebuilt from its bone-side faces)")
    parser.add_argument("--increments", type=int, default=None,
                        help="number of increments (default: 3, the lip-sliding paper's; with --tolerance, chosen)")
    parser.add_argument("--material", default=None, choices=MATERIALS,
                        help="soft-tissue material law (default: linear; with --tolerance, chosen)")
    parser.add_argument("--sliding", default=None, choices=SLIDINGS,
                        help="sliding model, mucosa+lip as in the lip-sliding paper (default: mucosa+lip; with "
                             "--tolerance, chosen)")
    parser.add_argument("--tolerance", type=tolerance_mm, default=None, metavar="MM",
                        help="choose the resolution, material, increments and sliding not given: the fastest "
                             "measured in the static ladder whose error (mm, 95th percentile of the nodal difference "
                             "to the most faithful model) is within MM; refused below the most faithful model's own "
                             "uncertainty, its difference to the fine face (default: none, the options above)")
    parser.add_argument("--solver", default="auto", choices=["auto", "superlu", "amg", "cholmod"],
                        help="linear solver (auto: chosen by the expected fill of the factor)")
    add_units(parser)
    add_axes(parser)
    parser.add_argument("--force", action="store_true",
                        help="accept movements beyond twice the physiological range (also for a --plan file)")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--no-preview", action="store_true", help="skip preview.png")


def simulate(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir
    from toolkit.static import SimulationOptions, load_case

    check_output_dir(args.out)
    chosen, fidelity = simulate_options(args)
    case = load_case(args.mesh, resolution=chosen["resolution"], plan=args.plan, bones=bones(args.bone),
                     force=args.force, units=args.units, axes=args.axes)
    result = case.simulate(fidelity=fidelity, increments=chosen["increments"], material=chosen["material"],
                           sliding=chosen["sliding"], options=SimulationOptions(solver=args.solver, progress=True))
    with uninterruptible():
        result.write(args.out, preview=not args.no_preview)
    s = result.summary()
    for r in s["increments_report"]:
        print(f"increment {r['increment']}: {r['seconds_step1'] + r['seconds_step2']:.1f} s, {r['linear_solves']} "
              f"linear solves, {r['substeps']} sub-step(s), min scaled Jacobian {r['min_scaled_jacobian']:.3f}")
    print(f"{s['nodes']} nodes, {s['increments']} increments, {s['material']}, {s['sliding']}: "
          f"max displacement {s['max_displacement_mm']:.2f} mm, min scaled Jacobian {s['min_scaled_jacobian']:.3f}, "
          f"max penetration {s['max_penetration_mm']:.2e} mm, {s['wall_time_s']:.1f} s")
    print(f"wrote {args.out}/ (result.vtu: pre-operative face with 'displacement'; postop.vtu: post-operative face; "
          f"increments.xdmf, summary.json, plan.toml{'' if args.no_preview else ', preview.png'})")
    return 0


def simulate_options(args: argparse.Namespace):
    """The resolution, increments, material and sliding of ``simulate``: those given, the others
    chosen by ``--tolerance`` (the choice printed) or :data:`SIMULATE_DEFAULTS`; and the
    FidelityChoice (None without ``--tolerance``). On a ``--mesh`` the resolution is the mesh's."""
    given = {k: getattr(args, k) for k in SIMULATE_DEFAULTS if getattr(args, k) is not None}
    if args.tolerance is None:
        return {**SIMULATE_DEFAULTS, **given}, None
    from toolkit.common.fidelity import choose_fidelity

    choice = choose_fidelity("static", args.tolerance, fixed=given, own_mesh=args.mesh is not None)
    print(choice.describe())
    return {**SIMULATE_DEFAULTS, **choice.options}, choice


def condyles(text: str):
    """``X,Y,Z:X,Y,Z`` (mm, left then right) or a file of two lines -> two points."""
    return two_points(text, "--condyles", "52.9,-18,21.6:-52.9,-18,21.6")


def add_database_arguments(parser: argparse.ArgumentParser) -> None:
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--resolution", default="coarse", choices=RESOLUTIONS, help="phantom resolution")
    source.add_argument("--mesh", type=Path,
                        help="simulate on this meshed face (.vtu/.inp/.xdmf, e.g. from `toolkit mesh`) instead of "
                             "the phantoms: one subject, plans placed by its landmarks (docs/own-face.md)")
    parser.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE",
                        help="with --mesh: bone surface of a segment, as for simulate (default: the mesh's "
                             "bone-side faces)")
    parser.add_argument("--condyles", type=condyles, default=None, metavar="X,Y,Z:X,Y,Z",
                        help="with --mesh: left (x > 0) and right condyle in mm, the pivots of the mandible "
                             "(default: the top of each proximal segment's surface)")
    add_units(parser)
    add_axes(parser, "the --mesh and --bone files and --condyles")
    parser.add_argument("--subjects", type=int, default=1,
                        help="number of phantom subjects, >= 1: subject 0 is the default shape, subject k >= 1 "
                             "FaceShape.sample(k)")
    parser.add_argument("--plans", type=int, required=True, help="plans per subject")
    parser.add_argument("--mode", default="sagittal", choices=["sagittal", "full"], help="plan directions")
    parser.add_argument("--increments", type=int, default=3, help="increments per simulation")
    parser.add_argument("--material", default="linear", choices=MATERIALS, help="soft-tissue material law")
    parser.add_argument("--sliding", default="mucosa+lip", choices=SLIDINGS,
                        help="sliding model (mucosa+lip: the lip-sliding paper)")
    parser.add_argument("--poisson-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                        help="draw Poisson's ratio per simulation, for models with material channels "
                             "(default: none, Poisson's ratio 0.47 as in the lip-sliding paper)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the plan sampling")
    add_database_run(parser, "simulations")


def database(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_file
    from toolkit.static.database import DatabaseConfig, build_database

    check_output_file(args.out, what="database file")
    settings = dict(subjects=args.subjects, plans=args.plans, mode=args.mode, increments=args.increments,
                    material=args.material, sliding=args.sliding, seed=args.seed,
                    poisson_range=tuple(args.poisson_range) if args.poisson_range else None)
    if args.mesh is None:
        if args.bone or args.condyles or args.axes != "toolkit":
            given = "--bone" if args.bone else "--condyles" if args.condyles else f"--axes {args.axes}"
            raise ValueError(f"{given} applies to a meshed face; give --mesh FACE.vtu, or leave it out for the "
                             "phantoms")
        config = DatabaseConfig(resolution=args.resolution, **settings)
    else:
        from toolkit.static.database import database_subject

        config = DatabaseConfig.for_mesh(args.mesh, bones(args.bone), args.condyles, args.units, args.axes, **settings)
        database_subject(config, 0)  # reads the mesh and places the plans: its errors before any output
    with dask_client(args.dask, args.workers) as client:
        report = build_database(args.out, config, executor=client, workers=args.workers, retry_failed=args.retry_failed)
    print(f"{len(report.done)} simulations done, {len(report.skipped)} already there, {len(report.failed)} failed "
          f"in {report.seconds:.1f} s -> {args.out}")
    for key, reason in list(report.failed.items())[:10]:
        print(f"  failed {key}: {reason[:160]}")
    return 0


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--data", required=True, type=Path, help="database (.h5) from `toolkit static database`")
    parser.add_argument("--out", required=True, type=Path, help="model directory")
    parser.add_argument("--variant", default="hard", choices=["explicit", "implicit", "hard"],
                        help="boundary types as inputs with exact boundary values (hard, the most accurate measured), "
                             "boundary types as inputs (explicit, the PointNet++ paper) or none (implicit)")
    parser.add_argument("--extra-channels", action="store_true",
                        help="mucosa/lip one-hot, jaw side, mucosa bone motion")
    parser.add_argument("--material-channels", action="store_true", help="Poisson's ratio per node")
    parser.add_argument("--linear-prior", action=argparse.BooleanOptionalAction, default=True,
                        help="learn the residual over the linear influence-matrix solution (given as input, added "
                             "back); --no-linear-prior with --variant explicit is the PointNet++ paper's model "
                             "(default: on)")
    parser.add_argument("--network", default="small", choices=["paper", "small", "tiny"], help="network size")
    parser.add_argument("--test-subjects", type=int, nargs="*", default=None,
                        help="hold these subjects out for testing (default: 70/10/20 split by simulation)")
    parser.add_argument("--epochs", type=positive_int, default=100, help="maximum epochs")
    parser.add_argument("--batch-size", type=positive_int, default=8, help="samples per batch")
    parser.add_argument("--lr", type=positive_float, default=1e-3, help="learning rate")
    parser.add_argument("--lr-schedule", default="constant", choices=["constant", "cosine"],
                        help="cosine: decay to 1%% of --lr over the epochs (or over --max-minutes when given)")
    parser.add_argument("--max-minutes", type=positive_float, default=None, help="training time limit (default: none)")
    parser.add_argument("--seed", type=int, default=0, help="weights, batch order and split")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--resume", action="store_true", help="continue from OUT/checkpoint.pt")


def train(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_model_dir
    from toolkit.static.features import FeatureSpec
    from toolkit.static.surrogate import SurrogateConfig, train_surrogate

    check_model_dir(args.out, resume=args.resume)
    config = SurrogateConfig(
        FeatureSpec(args.variant, args.extra_channels, args.material_channels, args.linear_prior),
        network=args.network,
        coarse_radii=_coarse_radii(args.data),
        split="subjects" if args.test_subjects else "plans", test_subjects=tuple(args.test_subjects or ()),
        epochs=args.epochs, batch_size=args.batch_size, lr=args.lr, seed=args.seed, device=args.device,
        max_seconds=None if args.max_minutes is None else 60 * args.max_minutes, lr_schedule=args.lr_schedule)
    model = train_surrogate(args.data, config, out=args.out, resume=args.resume)
    x = model.bundle.extra
    print(f"trained {config.features.variant} PointNet++ ({x['parameters']:,} parameters) on {x['split']['train']} "
          f"samples in {x['train_seconds']:.0f} s: best epoch {x['best_epoch']} ({x['stop_reason']}) -> {args.out}")
    return 0


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory")
    parser.add_argument("--data", required=True, type=Path, help="database (.h5) to score it on")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--no-preview", action="store_true", help="skip error_map.png")


def evaluate(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir
    from toolkit.static.database import subject_mesh
    from toolkit.static.surrogate import Surrogate, evaluate_surrogate, write_evaluation

    check_output_dir(args.out)
    model = Surrogate.load(args.model, device=args.device)
    result = evaluate_surrogate(model, args.data)
    mesh = None if args.no_preview else subject_mesh(args.data, 0)
    with uninterruptible():
        write_evaluation(result, args.out, mesh)
    m = result.metrics
    print(f"scored: {m['scored']}")
    print(f"{m['samples']} samples: mean error {m['mean_error_mm']:.3f} mm (median {m['median_error_mm']:.3f}, p95 "
          f"{m['p95_error_mm']:.3f}, max {m['max_error_mm']:.3f}); free nodes {m['free_mean_error_mm']:.3f}, lips "
          f"{m['lips_mean_error_mm']:.3f}; {m['inference_ms']:.1f} ms per prediction vs {m['fe_ms']:.0f} ms FE per "
          f"increment -> {args.out}/metrics.json")
    return 0


#: :data:`toolkit.static.trust.SCALES` and ``ANSWERERS`` (named here so that building the parser
#: imports no numerical library; a test keeps them equal)
STATIC_SCALES = ("disagreement", "constant")
STATIC_ANSWERERS = ("auto", "network", "baseline")


def add_calibrate_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory (the calibration is saved in it)")
    parser.add_argument("--data", required=True, type=Path,
                        help="the model's training database (its test plans are used) or another of its settings "
                             "(every plan the model did not see)")
    parser.add_argument("--train-data", type=Path, default=None,
                        help="the database the model was trained on, when --data is another one (default: --data)")
    parser.add_argument("--coverage", type=probability, default=0.9,
                        help="probability that the error bound holds for a plan like these")
    parser.add_argument("--scale", choices=STATIC_SCALES + ("auto",), default="auto",
                        help="disagreement: with the sliding response + POD residual baseline; constant: one bound "
                             "for all; auto: both, and `predict --tolerance` takes the pair (with --answerer) "
                             "whose expected time per answer over these plans is least at its tolerance")
    parser.add_argument("--answerer", choices=STATIC_ANSWERERS, default=STATIC_ANSWERERS[0],
                        help="whose answer `predict --tolerance` gives and bounds: the network, the sliding "
                             "response + POD residual baseline, or auto (see --scale)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")


def calibrate(args: argparse.Namespace) -> int:
    from toolkit.static.surrogate import Surrogate
    from toolkit.static.trust import calibrate_surrogate

    model = Surrogate.load(args.model, device=args.device)
    cal = calibrate_surrogate(model, args.data, coverage=args.coverage, scale=args.scale, training=args.train_data,
                              answerer=args.answerer)
    with uninterruptible():
        cal.save(args.model)
    for who, key in (("network", "error_mm"), ("baseline", "baseline_error_mm")):
        errors = sorted(c[key] for c in cal.cases)
        print(f"{who}: answer error (p95 over nodes) median {errors[len(errors) // 2]:.2f} mm, max {errors[-1]:.2f} "
              f"mm over {cal.bound.n} held-out plans ({cal.source['plans']}); {cal.scale} scale x "
              f"{cal.bounds[who].factor:.3g} bounds it at {cal.bound.coverage:.0%}")
    pairs = ", ".join(f"{a} with the {s} scale" for s, a in cal.candidates)
    print(f"`predict --tolerance` answers with the pair whose expected time per answer is least at its tolerance "
          f"among: {pairs} -> {args.model}/calibration.json")
    return 0


def add_predict_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, type=Path, help="model directory")
    parser.add_argument("--plan", type=Path,
                        help="plan (.toml/.json) (default: the packaged bimaxillary plan, phantom only)")
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--mesh", type=Path,
                        help="face mesh with the phantom's node sets, needs --plan (default: the built-in phantom)")
    source.add_argument("--resolution", default=None, choices=RESOLUTIONS,
                        help="built-in phantom (default: the training database's)")
    parser.add_argument("--bone", action="append", default=[], metavar="SEGMENT=FILE",
                        help="as for simulate (default: the phantom's surfaces, or the mesh's bone-side faces)")
    parser.add_argument("--any-mesh", action="store_true",
                        help="predict on a mesh of another topology than the training meshes (PointNet++ reads a "
                             "point cloud; its accuracy on a remeshed face is in docs/own-face.md)")
    add_units(parser)
    add_axes(parser)
    parser.add_argument("--force", action="store_true",
                        help="accept movements beyond twice the physiological range (also for a --plan file)")
    parser.add_argument("--tolerance", type=positive_float, default=None, metavar="MM",
                        help="answer within this error (mm, 95th percentile of the nodal error): the surrogate's "
                             "prediction when its calibrated estimate is within it and the inputs are like its "
                             "training data, else the FE of the same plan (needs `toolkit static calibrate`)")
    parser.add_argument("--coverage", type=probability, default=None,
                        help="with --tolerance: the estimate's coverage (default: the calibration's)")
    parser.add_argument("--material", choices=MATERIALS, default=None,
                        help="with --tolerance: the tissue material (default: the training database's; another "
                             "one is answered by the FE)")
    parser.add_argument("--device", default="cpu", help="cpu, cuda or auto")
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--no-preview", action="store_true", help="skip preview.png")


def predict(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir
    from toolkit.static import load_case
    from toolkit.static.surrogate import Surrogate

    check_output_dir(args.out)
    model = Surrogate.load(args.model, device=args.device)
    database = model.bundle.data["database"]
    if args.mesh is None and database.get("mesh") is not None and not (args.any_mesh and args.resolution):
        raise ValueError(f"the model was trained on the meshed face {database['mesh']}: give it with --mesh and a "
                         "--plan (pivot_mm for every rotating segment), or predict on a phantom anyway with "
                         "--any-mesh --resolution R")
    resolution = args.resolution or database["resolution"]
    case = load_case(args.mesh, resolution=resolution, plan=args.plan, bones=bones(args.bone), force=args.force,
                     units=args.units, axes=args.axes)
    if args.tolerance is None:
        if args.coverage is not None or args.material is not None:
            raise ValueError("--coverage and --material go with --tolerance (an answer within a tolerance)")
        result = model.predict_plan(case.subject, case.plan, segments=case.segments, any_mesh=args.any_mesh)
    else:
        return _predict_within(args, model, case)
    with uninterruptible():
        result.write(args.out, preview=not args.no_preview)
    s = result.summary()
    print(f"{s['nodes']} nodes, {s['increments']} increments predicted in {s['wall_time_s'] * 1e3:.0f} ms: max "
          f"displacement {s['max_displacement_mm']:.2f} mm, min scaled Jacobian {s['min_scaled_jacobian']:.3f} -> "
          f"{args.out}/ (result.vtu, postop.vtu, increments.xdmf, summary.json, plan.toml)")
    from toolkit.common.training import describe_extrapolation

    print(f"plan: {describe_extrapolation(s['extrapolation'])}")
    checks = s["checks"]["answer"]
    if not checks["passed"]:
        print(f"warning: the answer failed its checks ({'; '.join(checks['problems'])}); summary.json flags it "
              "(checks.answer.passed false). Rerun with --tolerance MM to have the FE answer instead",
              file=sys.stderr)
    return 0


def _predict_within(args, model, case) -> int:
    from toolkit.common.training import describe_extrapolation
    from toolkit.static.trust import Calibration, answer

    calibration = Calibration.load(args.model)
    if args.coverage is not None:
        calibration = calibration.at(args.coverage)
    result = answer(model, case.subject, case.plan, args.tolerance, segments=case.segments, calibration=calibration,
                    material=args.material, any_mesh=args.any_mesh)
    with uninterruptible():
        result.write(args.out, preview=not args.no_preview)
    s = result.summary()
    a, sec = s["answer"], result.seconds
    who = {"surrogate": "the surrogate", "baseline": "the sliding response + POD residual baseline", "fe": "the FE"}
    print(f"answered by {who[a['answered_by']]}: {a['reason']}")
    print(f"plan: {describe_extrapolation(a['out_of_distribution']['plan'])}")
    print(f"{s['nodes']} nodes: max displacement {s['max_displacement_mm']:.2f} mm; surrogate "
          f"{sec['surrogate']:.2f} s, estimate {sec['estimate']:.2f} s, FE {sec['fe']:.2f} s -> {args.out}/ "
          "(result.vtu, postop.vtu, increments.xdmf, summary.json, plan.toml)")
    return 0


def bones(specs: list[str]) -> dict[str, Path]:
    """``["lefort=maxilla.stl", ...]`` (the ``--bone`` values) -> ``{"lefort": Path("maxilla.stl"), ...}``."""
    out = {}
    for spec in specs:
        name, sep, path = spec.partition("=")
        if not sep or not name or not path:
            raise ValueError(f"--bone {spec!r}: expected SEGMENT=FILE, e.g. --bone lefort=maxilla.stl")
        if name in out:
            raise ValueError(f"--bone {name}= given twice")
        out[name] = Path(path)
    return out


#: meshes with fewer nodes take the coarse PointNet++ radii (the coarse phantom has ~800, the paper one ~4,000)
COARSE_NODES = 2000


def _coarse_radii(path) -> bool:
    """Whether a database's meshes are coarse: the coarse phantom, or a meshed face under
    :data:`COARSE_NODES` nodes (a database that does not say is the paper phantom's)."""
    import json

    from toolkit.common.training.database import Database

    config = json.loads(Database.open_attrs(Path(path)).get("config", "{}"))
    if config.get("mesh") is None:
        return config.get("resolution", "paper") == "coarse"
    from toolkit.static.database import subject_mesh

    return subject_mesh(path, 0).n_points < COARSE_NODES


COMMANDS = {
    "simulate": Command(
        help="simulate a surgical plan on a face",
        description="Run the incremental FE simulation (mucosa and lip sliding) and write result.vtu (reference "
                    "mesh + displacement), postop.vtu (post-operative face), increments.xdmf, summary.json, plan.toml "
                    "and preview.png.",
        add_arguments=add_simulate_arguments, run=simulate,
        interrupted=NOTHING_WRITTEN + " (the files are written after the last increment)"),
    "database": Command(
        help="build the surrogate's learning database",
        description="Simulate sampled plans on phantom subjects or on a meshed face (--mesh); every increment is "
                    "a learning sample (the PointNet++ paper). Resumable: a rerun skips finished simulations; "
                    "failures are recorded with their reason. Ctrl-C loses no finished simulation.",
        add_arguments=add_database_arguments, run=database, interrupted=SIMULATIONS_KEPT),
    "train": Command(
        help="train the PointNet++ surrogate on a database",
        description="Train PointNet++ (the PointNet++ paper) on a static database; writes model.pt and config.json "
                    "(checkpoint.pt while training; --resume continues it).",
        add_arguments=add_train_arguments, run=train, interrupted=EPOCHS_KEPT),
    "evaluate": Command(
        help="score a surrogate on a database",
        description="Mean Euclidean nodal error per sample (all, free, lips), inference and FE times; writes "
                    "metrics.json, per_sample.csv and error_map.png.",
        add_arguments=add_evaluate_arguments, run=evaluate, interrupted=NOTHING_WRITTEN),
    "calibrate": Command(
        help="calibrate a surrogate's error estimate",
        description="Measure the surrogate's answer error on whole plans of a database it did not see and calibrate "
                    "an error bound at a stated coverage (split-conformal); writes calibration.json and "
                    "calibration.npz into the model directory, which `predict --tolerance` reads.",
        add_arguments=add_calibrate_arguments, run=calibrate, interrupted=NOTHING_WRITTEN),
    "predict": Command(
        help="predict a plan with a surrogate",
        description="Run a plan with the surrogate instead of the FE; writes the files of `toolkit static simulate`. "
                    "With --tolerance, the FE answers instead when the calibrated error estimate exceeds it or the "
                    "inputs lie beyond the training data; summary.json says which answered and why.",
        add_arguments=add_predict_arguments, run=predict, interrupted=NOTHING_WRITTEN),
}
