"""Render the figures of the documentation pages into ``docs/figures/``.

    python docs/figures/make_figures.py            # all figures, about 1 minute on 2 cores
    python docs/figures/make_figures.py phantom    # only some: phantom, static, impact, ladder, own_face

Every figure names its view and length unit in its title, shows the axes (x lateral, y anterior,
z superior) and the unit of its colour bar (``toolkit.common.plotting.render``). Rendering is
off-screen (pyvista through EGL); nothing needs a display.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parents[1] / "benchmarks" / "results"
SIZE = (800, 600)


def _shrink(path: Path) -> Path:
    """Re-save a PNG with an adaptive palette (renders are flat-shaded: 256 colours keep them)."""
    from PIL import Image

    with Image.open(path) as image:
        small = image.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    small.save(path, optimize=True)
    return path


def phantom() -> list[Path]:
    """The coarse hexahedral face with its boundary node sets, from the front and from inside."""
    from toolkit.common import face_hex
    from toolkit.common.plotting import render

    mesh = face_hex("coarse").mesh
    sets = mesh.node_sets
    front = {name: sets[name] for name in ("fixed", "lip_sliding")}
    inside = {name: sets[name] for name in ("fixed", "maxilla", "mandible", "mucosa_sliding")}
    return [
        _shrink(render(mesh, HERE / "phantom_front.png", camera="front", node_sets=front, window_size=SIZE,
                       title="coarse face phantom")),
        _shrink(render(mesh, HERE / "phantom_inside.png", camera="inner", node_sets=inside, window_size=SIZE,
                       title="coarse face phantom")),
    ]


def static() -> list[Path]:
    """The packaged bimaxillary plan on the paper face: displacement magnitude on the deformed face."""
    from toolkit.common import face_hex
    from toolkit.common.plotting import render
    from toolkit.static import default_plan, simulate

    face = face_hex("paper")
    result = simulate(face, default_plan(face), increments=3, material="linear", sliding="mucosa+lip")
    u = result.displacement
    magnitude = np.linalg.norm(u, axis=1)
    common = dict(scalars=magnitude, displacement=u, scalar_label="displacement (mm)",
                  clim=(0.0, float(magnitude.max())), window_size=SIZE, cmap="viridis")
    return [
        _shrink(render(result.reference, HERE / "static_front.png", camera="front",
                       title="default plan, paper face, post-operative", **common)),
        _shrink(render(result.reference, HERE / "static_side.png", camera="left",
                       title="default plan, paper face, post-operative",
                       **common)),
    ]


def impact() -> list[Path]:
    """A quasi-static impact on the coarse face (rigid ball, 30 mm/s, 1.8 s): von Mises at the end."""
    from toolkit.common import ball
    from toolkit.common.plotting import render
    from toolkit.impact import default_scene, simulate
    from toolkit.impact.simulate import ball_start

    scene = (default_scene(velocity=30.0).with_face(resolution="coarse").with_ball(rigid=True)
             .with_fidelity(integrator="quasi-static"))
    result = simulate(scene)
    face = result.face
    u = result.displacement[-1]
    centre0 = ball_start(scene, face.points[face.node_set("skin")])
    travel = np.asarray(scene.ball.direction, float) * scene.ball.velocity * result.times[-1]
    sphere = ball(scene.ball.radius, "coarse", order=1, centre=tuple(centre0 + travel))
    extra = [(sphere, {"style": "wireframe", "color": "#5a7bb5", "opacity": 0.25, "line_width": 0.5})]
    magnitude = np.linalg.norm(u, axis=1)
    return [
        _shrink(render(face, HERE / "impact_side.png", scalars=magnitude, displacement=u, camera="left",
                       scalar_label="displacement (mm)", window_size=SIZE, extra=extra,
                       title=f"ball at 30 mm/s, t = {result.times[-1]:.1f} s (ball moves -y)")),
        _shrink(render(face, HERE / "impact_von_mises.png", scalars=result.von_mises[-1], displacement=u,
                       camera="front", scalar_label="von Mises stress (MPa)",
                       clim=(0.0, float(result.von_mises[-1].max())), window_size=SIZE,
                       title=f"ball at 30 mm/s, t = {result.times[-1]:.1f} s (ball not drawn)")),
    ]


def ladder() -> list[Path]:
    """The impact ladder's trade-off (wall time against skin RMSE), from its committed results."""
    import pandas as pd

    from toolkit.common.plotting import plot_tradeoff

    path = RESULTS / "impact_ladder.csv"
    if not path.exists():
        print(f"skipped ladder: {path} not found (run benchmarks/impact_ladder.py)", file=sys.stderr)
        return []
    table = pd.read_csv(path)
    ok = table[(table.status == "ok") & (table.rmse_displacement_mm > 0)]  # the references have no error
    if ok.empty:
        print(f"skipped ladder: no run of {path} has an explicit reference to compare with", file=sys.stderr)
        return []
    labels = [f"{r.resolution}, tet{4 if r.order == 1 else 10}, {r.ball} ball, "
              + (f"quasi-static {r.tolerance:g}" if r.integrator == "quasi-static"
                 else f"mass scaling {r.mass_scaling:g}")
              for r in ok.itertuples()]
    out = HERE / "impact_ladder.png"
    plot_tradeoff(ok.wall_time_s.to_numpy(), ok.rmse_displacement_mm.to_numpy(), labels,
                  xlabel="wall time per simulation (s, one core of an AMD EPYC)",
                  ylabel="skin displacement RMSE to the reference (mm)",
                  title="impact scene at 30 mm/s, 1.8 s: fidelity options", path=out)
    return [_shrink(out)]


def own_face() -> list[Path]:
    """``toolkit mesh`` on the paper phantom's surfaces: its labels.png."""
    from toolkit.common.phantoms.phantom import face_hex
    from toolkit.mesh import mesh_face
    from toolkit.mesh.face import render_labels
    from toolkit.mesh.phantom import phantom_surfaces

    s = phantom_surfaces(face_hex("paper"))
    face = mesh_face(s.tissue, s.bones, s.commissures, size_mm=5.0, order=2)
    return [_shrink(render_labels(face, HERE / "own_face_labels.png"))]


FIGURES = {"phantom": phantom, "static": static, "impact": impact, "ladder": ladder, "own_face": own_face}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*", metavar="NAME",
                        help=f"figures to render, among {', '.join(FIGURES)} (default all)")
    args = parser.parse_args(argv)
    unknown = sorted(set(args.names) - set(FIGURES))
    if unknown:
        parser.error(f"unknown figures {unknown}; expected some of {sorted(FIGURES)}")
    from toolkit import set_threads

    set_threads(1)
    for name in args.names or FIGURES:
        for path in FIGURES[name]():
            print(f"{path.relative_to(HERE.parents[1])}: {path.stat().st_size / 1024:.0f} kB")


if __name__ == "__main__":
    main()
