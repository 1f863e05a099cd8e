"""Headless figures: a real off-screen render and matplotlib curves."""

import numpy as np
import pytest

from toolkit.common.phantoms.phantom import face_hex


def _image(path):
    from matplotlib.image import imread

    return imread(path)


def test_headless_render_shows_the_field(tmp_path):
    """Off-screen render (EGL, no X server) of the face coloured by a displacement field:
    a non-empty PNG whose pixels are not all background."""
    pytest.importorskip("pyvista")
    from toolkit.common.plotting import render

    mesh = face_hex("coarse").mesh
    u = np.zeros((mesh.n_points, 3))
    u[:, 1] = 0.05 * (mesh.points[:, 2] - mesh.points[:, 2].min())
    path = render(mesh, tmp_path / "face.png", scalars=u, displacement=u, title="|u| (mm)",
                  node_sets={"fixed": mesh.node_sets["fixed"]})
    img = _image(path)
    assert img.shape[0] > 100 and img.shape[1] > 100
    rgb = img[..., :3]
    background = np.all(rgb > 0.99, axis=-1)
    assert 0.05 < 1 - background.mean() < 0.95  # the face covers part of the frame
    colours = np.unique((rgb[~background] * 16).astype(int), axis=0)
    assert len(colours) > 20  # a colour map, not a flat silhouette


def test_a_node_set_has_one_colour_whichever_sets_are_shown(tmp_path):
    """A set's colour depends on its name only: ``mandible`` is drawn in the same colour with or
    without ``maxilla`` beside it (a segmentation that lost a set does not recolour the others),
    and a set of another name always gets the same colour of the palette."""
    pytest.importorskip("pyvista")
    from toolkit.common.plotting import SET_COLOURS, render, set_colour

    assert set_colour("mandible") == SET_COLOURS["mandible"] != set_colour("maxilla")
    assert set_colour("my_set") == set_colour("my_set")
    mesh = face_hex("coarse").mesh
    target = np.array([int(SET_COLOURS["mandible"][i:i + 2], 16) for i in (1, 3, 5)]) / 255

    def share(sets):
        rgb = _image(render(mesh, tmp_path / "sets.png", node_sets=sets, show_edges=False))[..., :3]
        return float(np.all(np.abs(rgb - target) < 0.08, axis=-1).mean())

    alone = share({"mandible": mesh.node_sets["mandible"]})
    with_others = share({k: mesh.node_sets[k] for k in ("maxilla", "mandible")})
    assert alone > 0.001 and with_others > 0.5 * alone


def test_render_mixed_mesh(tmp_path):
    """A mesh with hex8, wedge6 and tet4 blocks renders off-screen, coloured by a cell
    field over all blocks: a non-empty PNG that is not all background."""
    pytest.importorskip("pyvista")
    from toolkit.common.phantoms.mixed_bar import mixed_bar
    from toolkit.common.plotting import render

    mesh = mixed_bar(2)
    block_id = np.concatenate([np.full(b.n_cells, k, float) for k, b in enumerate(mesh.volume_blocks)])
    path = render(mesh, tmp_path / "mixed.png", scalars=block_id, camera="iso", title="block")
    assert path.stat().st_size > 0
    rgb = _image(path)[..., :3]
    background = np.all(rgb > 0.99, axis=-1)
    assert 0.05 < 1 - background.mean() < 0.95


def test_render_rejects_bad_scalars(tmp_path):
    from toolkit.common.plotting import render

    mesh = face_hex("coarse").mesh
    with pytest.raises(ValueError, match="expected n_points=771 or n_cells=440"):
        render(mesh, tmp_path / "x.png", scalars=np.zeros(5))
    with pytest.raises(KeyError, match="no point or cell field 'stress'"):
        render(mesh, tmp_path / "x.png", scalars="stress")
    with pytest.raises(ValueError, match="unknown camera 'top'"):
        render(mesh, tmp_path / "x.png", camera="top")


def test_curves_and_tradeoff_figures(tmp_path):
    from toolkit.common.plotting import plot_curves, plot_tradeoff

    t = np.linspace(0, 1.8, 50)
    fig = plot_curves(t, {"kinetic": t**2, "internal": t}, xlabel="time (s)", ylabel="energy (mJ)",
                      path=tmp_path / "energy.png")
    assert len(fig.axes[0].lines) == 2 and (tmp_path / "energy.png").stat().st_size > 1000
    plot_tradeoff([1.0, 10.0], [0.5, 0.05], ["coarse", "fine"], path=tmp_path / "ladder.png")
    assert _image(tmp_path / "ladder.png").std() > 0
    with pytest.raises(ValueError, match="curve 'bad' has shape"):
        plot_curves(t, {"bad": t[:3]}, xlabel="t", ylabel="y")
