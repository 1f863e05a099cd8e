"""``toolkit demo``: the coarse phantoms, checked and written, a static run and a short impact."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from toolkit.cli._common import RESOLUTIONS, Command
from toolkit.cli.phantom import build

MESHES = (("face_hex", "face-hex"), ("face_tet10", "face-tet10"), ("ball", "ball-tet10"))


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", required=True, type=Path, help="output folder")
    parser.add_argument("--resolution", default="coarse", choices=RESOLUTIONS, help="phantom resolution")
    parser.add_argument("--no-preview", action="store_true", help="skip the PNG previews")


def run(args: argparse.Namespace) -> int:
    from toolkit.common.outputs import check_output_dir

    out: Path = check_output_dir(args.out)
    out.mkdir(parents=True, exist_ok=True)
    t_all = time.perf_counter()
    rows = [_write_phantom(name, kind, args.resolution, out, render=not args.no_preview) for name, kind in MESHES]
    t0 = time.perf_counter()
    static = _static(args.resolution)
    static.write(out / "static", preview=not args.no_preview)
    st = static.summary()
    st_seconds = time.perf_counter() - t0
    t0 = time.perf_counter()
    impact = _impact(out / "impact", preview=not args.no_preview)
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


def _write_phantom(name: str, kind: str, resolution: str, out: Path, render: bool) -> dict:
    """Build, check and write one phantom (.inp, .vtu, optionally .png); its summary row."""
    from toolkit.common.meshes.io import write

    t0 = time.perf_counter()
    mesh = build(kind, resolution)
    sj = mesh.check().scaled_jacobian()
    write(out / f"{name}.inp", mesh)
    write(out / f"{name}.vtu", mesh)
    if render:
        from toolkit.common.plotting import render as render_png

        render_png(mesh, out / f"{name}.png", camera="inner" if name == "face_hex" else "iso",
                   node_sets=_preview_sets(mesh),
                   title=f"{name} ({resolution}): {mesh.n_points} nodes, {mesh.n_cells} elements")
    return {"mesh": name, "cell_type": mesh.volume_type, "nodes": mesh.n_points, "elements": mesh.n_cells,
            "min_scaled_jacobian": round(float(sj.min()), 4), "node_sets": sorted(mesh.node_sets),
            "element_sets": sorted(mesh.element_sets), "seconds": round(time.perf_counter() - t0, 2)}


def _static(resolution: str):
    """The packaged plan on the phantom: 3 increments, linear, mucosa and lip sliding."""
    from toolkit.static import load_case

    return load_case(resolution=resolution).simulate(increments=3, material="linear", sliding="mucosa+lip")


def _impact(out: Path, preview: bool):
    """A short coarse impact: the fastest fidelity options (see benchmarks/impact_ladder.py)."""
    from dataclasses import replace

    from toolkit.impact import default_scene, simulate

    scene = default_scene().with_face(resolution="coarse").with_ball(rigid=True)
    scene = replace(scene.with_fidelity(order=1, integrator="explicit", mass_scaling=100.0), duration=0.9, n_frames=9)
    return simulate(scene, out=out, preview=preview)


def _preview_sets(mesh) -> dict:
    """The boundary node sets of a phantom (or the ball's surface), for previews."""
    from toolkit.common.phantoms.phantom import BOUNDARY_SETS

    names = [n for n in BOUNDARY_SETS if n in mesh.node_sets]
    names = names or [n for n in ("fixed", "surface") if n in mesh.node_sets]
    return {n: mesh.node_sets[n] for n in names}


COMMAND = Command(
    help="build, validate and write the coarse phantoms with previews",
    description="Build the coarse face (hex8, tet10) and ball phantoms, check every element, and write them as "
                "Abaqus .inp and .vtu with PNG previews; then run the packaged surgical plan on the face (static/) "
                "and a short rigid-ball impact (impact/), and write summary.json.",
    add_arguments=add_arguments,
    run=run,
)
