"""Figures: off-screen mesh renders (pyvista) and curves (matplotlib).

Rendering works on a headless machine and in CI: VTK is pointed at its EGL
(Mesa) render window when there is no X display (see
:func:`toolkit.common.runtime.configure_headless_rendering`); the Debian packages
``libegl1`` and ``libgl1-mesa-dri`` provide it (``.ci/run`` installs them when
missing).

Matplotlib figures are built with :class:`matplotlib.figure.Figure` (no pyplot
state, no GUI backend), so they work headless and display in Jupyter.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from toolkit.common.meshes.convert import to_pyvista
from toolkit.common.meshes.io import atomic_path
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.runtime import configure_headless_rendering

__all__ = ["render", "plot_curves", "plot_tradeoff", "CAMERAS", "SET_COLOURS", "set_colour"]

_SET_COLOURS = ["#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#17becf", "#e377c2", "#8c564b", "#bcbd22"]
#: the colour of each boundary node set, the same in every image whichever sets a mesh has
SET_COLOURS = {"fixed": "#1f77b4", "maxilla": "#d62728", "mandible": "#2ca02c", "mucosa_sliding": "#9467bd",
               "lip_sliding": "#ff7f0e", "skin": "#17becf", "bone": "#8c564b"}


def set_colour(name: str) -> str:
    """The colour of node set ``name``: :data:`SET_COLOURS`, else one of a palette chosen by the
    name (not by its place in a list), so that it is the same in every image."""
    import zlib

    return SET_COLOURS.get(name) or _SET_COLOURS[zlib.crc32(name.encode()) % len(_SET_COLOURS)]

#: camera direction (from the focal point) and view-up, in the phantom axes
#: (x lateral, y anterior, z superior)
CAMERAS = {
    "front": ((0.0, 1.0, 0.0), (0.0, 0.0, 1.0)),
    "left": ((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "right": ((-1.0, 0.0, 0.0), (0.0, 0.0, 1.0)),
    "iso": ((0.8, 1.0, 0.45), (0.0, 0.0, 1.0)),
    "inner": ((0.45, -1.0, 0.3), (0.0, 0.0, 1.0)),
}


def _scalars(mesh: Mesh, scalars) -> tuple[np.ndarray | None, str | None, bool]:
    """Resolve ``scalars`` to (values, label, on_points)."""
    if scalars is None:
        return None, None, True
    if isinstance(scalars, str):
        if scalars in mesh.point_data:
            values, on_points = np.asarray(mesh.point_data[scalars]), True
        elif scalars in mesh.cell_data:
            values, on_points = np.asarray(mesh.cell_data[scalars]), False
        else:
            raise KeyError(f"no point or cell field {scalars!r}; the mesh has point fields {sorted(mesh.point_data)}"
                           f" and cell fields {sorted(mesh.cell_data)}")
        label = scalars
    else:
        values = np.asarray(scalars, dtype=float)
        if values.shape[0] == mesh.n_points:
            on_points = True
        elif values.shape[0] == mesh.n_cells:
            on_points = False
        else:
            raise ValueError(f"scalars have {values.shape[0]} rows; expected n_points={mesh.n_points} "
                             f"or n_cells={mesh.n_cells}")
        label = "value"
    if values.ndim == 2:
        values = np.linalg.norm(values, axis=1)
        label = f"|{label}|"
    if not np.isfinite(values).all():
        raise ValueError(f"scalars {label!r} hold NaN/inf")
    return values.astype(float), label, on_points


def render(
    mesh: Mesh,
    path: str | os.PathLike,
    scalars: str | np.ndarray | None = None,
    *,
    displacement: np.ndarray | None = None,
    camera: str = "front",
    cmap: str = "viridis",
    clim: tuple[float, float] | None = None,
    title: str | None = None,
    scalar_label: str | None = None,
    show_edges: bool = True,
    window_size: tuple[int, int] = (900, 700),
    node_sets: Mapping[str, np.ndarray] | None = None,
    extra: Sequence[tuple[Mesh, dict]] = (),
) -> Path:
    """Render ``mesh`` (its outer surface) to a PNG, off-screen, with the view's name and the
    length unit after ``title``, the axes' directions in the lower left corner and, with
    ``node_sets``, a legend in the lower right (each set in its :func:`set_colour`).

    Parameters
    ----------
    mesh : Mesh (volume or surface, any mix of cell blocks), mm
    path : PNG file to write (atomically)
    scalars : name of a point/cell field, or ``(n_points,)``/``(n_cells,)`` values;
        ``(n, 3)`` vectors are shown by magnitude (e.g. displacement in mm, von
        Mises stress in MPa)
    displacement : (n_points, 3) mm, drawn deformed when given
    camera : one of :data:`CAMERAS`
    clim : colour range; default the data range
    node_sets : name -> node indices to mark as coloured points with a legend
        (e.g. the boundary sets), each in its :func:`set_colour`
    extra : further ``(mesh, pyvista add_mesh keyword arguments)`` to draw, e.g. a ball

    Returns
    -------
    Path of the PNG.
    """

    if camera not in CAMERAS:
        raise ValueError(f"unknown camera {camera!r}; expected one of {sorted(CAMERAS)}")
    configure_headless_rendering()
    import pyvista as pv

    values, label, on_points = _scalars(mesh, scalars)
    shown = mesh if displacement is None else mesh.translated(displacement)
    grid = to_pyvista(shown)
    if values is not None:
        (grid.point_data if on_points else grid.cell_data)["_scalars"] = values
    surface = grid.extract_surface(algorithm="dataset_surface") if mesh.volume_types else grid
    plotter = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        plotter.set_background("white")
        kwargs = dict(show_edges=show_edges, edge_color="#404040", line_width=0.5, smooth_shading=False)
        if values is not None:
            # upright on the right, its title above it and its labels beside it: none overlaps another
            bar = {"title": scalar_label or label, "color": "black", "vertical": True, "position_x": 0.84,
                   "position_y": 0.2, "width": 0.06, "height": 0.6, "fmt": "%.3g", "n_labels": 5,
                   "title_font_size": 16, "label_font_size": 14}
            plotter.add_mesh(surface, scalars="_scalars", cmap=cmap, clim=clim, scalar_bar_args=bar, **kwargs)
        else:
            plotter.add_mesh(surface, color="#f1c9a5", **kwargs)
        for name, ids in (node_sets or {}).items():
            ids = np.asarray(ids, dtype=np.int64)
            if ids.size:
                plotter.add_points(shown.points[ids], color=set_colour(name), label=name,
                                   point_size=8, render_points_as_spheres=True)
        if node_sets:  # in the lower right corner, beside the face (centred) rather than over it
            plotter.add_legend(bcolor="white", face="circle", size=(0.2, 0.22), loc="lower right")
        for other, opts in extra:
            g = to_pyvista(other)
            plotter.add_mesh(g.extract_surface(algorithm="dataset_surface"),
                             **{"color": "#9fb7d9", "opacity": 0.6, **opts})
        view = f"{camera} view" if camera != "inner" else "view from inside"
        plotter.add_text(f"{title} ({view}, mm)" if title else f"{view}, mm", font_size=11, color="black")
        plotter.add_axes(color="black")  # the toolkit's axes: x lateral, y anterior, z superior
        direction, up = CAMERAS[camera]
        centre = np.asarray(surface.center)
        d = np.asarray(direction) / np.linalg.norm(direction)
        plotter.camera_position = [tuple(centre + 100.0 * d), tuple(centre), up]
        plotter.reset_camera()
        with atomic_path(Path(path).with_suffix(".png")) as tmp:
            plotter.screenshot(str(tmp))
    finally:
        plotter.close()
    return Path(path).with_suffix(".png")


def plot_curves(
    x: np.ndarray,
    curves: Mapping[str, np.ndarray],
    *,
    xlabel: str,
    ylabel: str,
    title: str | None = None,
    path: str | os.PathLike | None = None,
    logy: bool = False,
):
    """Line plot of several named curves over a shared ``x`` (e.g. energies over time).

    Parameters
    ----------
    x : (n,) e.g. time in s
    curves : name -> (n,) values (say the unit in ``ylabel``)
    path : optional PNG/PDF to write

    Returns
    -------
    matplotlib.figure.Figure
    """
    from matplotlib.figure import Figure

    x = np.asarray(x, dtype=float)
    fig = Figure(figsize=(6.4, 4.0), layout="constrained")
    ax = fig.add_subplot()
    for name, y in curves.items():
        y = np.asarray(y, dtype=float)
        if y.shape != x.shape:
            raise ValueError(f"curve {name!r} has shape {y.shape}, expected {x.shape} like x")
        ax.plot(x, y, label=name)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if logy:
        ax.set_yscale("log")
    if title:
        ax.set_title(title)
    if len(curves) > 1:
        ax.legend()
    ax.grid(alpha=0.3)
    if path is not None:
        _save(fig, path)
    return fig


def plot_tradeoff(
    cost: np.ndarray,
    error: np.ndarray,
    labels: Sequence[str],
    *,
    xlabel: str = "wall time (s)",
    ylabel: str = "error (mm)",
    title: str | None = None,
    path: str | os.PathLike | None = None,
):
    """Scatter of error against cost on log-log axes, one labelled point per option.

    The speed/accuracy ladders of the benchmarks use it.
    """
    from matplotlib.figure import Figure

    cost, error = np.asarray(cost, dtype=float), np.asarray(error, dtype=float)
    if cost.shape != error.shape or cost.shape[0] != len(labels):
        raise ValueError(f"cost {cost.shape}, error {error.shape} and {len(labels)} labels must agree")
    fig = Figure(figsize=(6.4, 4.8), layout="constrained")
    ax = fig.add_subplot()
    ax.scatter(cost, error)
    for c, e, lab in zip(cost, error, labels):
        ax.annotate(lab, (c, e), fontsize=7, xytext=(3, 3), textcoords="offset points")
    ax.set_xscale("log")
    if np.all(error > 0):
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    if path is not None:
        _save(fig, path)
    return fig


def _save(fig, path) -> None:

    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, format=path.suffix.lstrip(".") or "png")
