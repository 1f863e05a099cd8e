"""Mucosa off the bone, as segmented faces come: the phantom with its bone surfaces moved away
from the tissue (:func:`toolkit.common.phantoms.off_bone.off_bone`), and the sliding constraint that
keeps each mucosa node at its pre-operative distance from its moving bone. Units mm."""

import numpy as np
import pytest

from toolkit.common.analysis.surface_distance import beyond_rim_onto_plane, closest_points
from toolkit.common.phantoms.off_bone import off_bone
from toolkit.common.phantoms.phantom import face_hex
from toolkit.static.boundary import NodeType
from toolkit.static.plan import default_plan
from toolkit.static.simulate import SimulationOptions, simulate


@pytest.fixture(scope="module")
def phantom():
    return face_hex("coarse")


@pytest.fixture(scope="module")
def lifted(phantom):
    return off_bone(phantom)


def _distance_to_bone(face, plan, nodes, segment, names, x):
    """Distance of nodes at ``x`` to their segment's bone surface moved by ``plan`` (extended
    beyond its rim by the planes of its rim triangles), mm."""
    d = np.full(nodes.size, np.nan)
    for s, name in enumerate(names):
        sel = np.flatnonzero(segment[nodes] == s)
        if sel.size:
            surf = face.segments[name].surface
            moved = plan.motion(name).apply(surf.points)
            cp = closest_points(x[nodes[sel]], moved, surf.cells["tri3"])
            d[sel] = beyond_rim_onto_plane(x[nodes[sel]], cp, moved, surf.cells["tri3"])[0].distance
    return d


def test_off_bone_moves_only_the_bone_surfaces_away_from_the_tissue(phantom, lifted):
    """The mesh is untouched; each bone surface vertex moved by 0 < d <= 10 mm along its
    normal, away from the skin; the mucosa then lies off its bone (median 1-4 mm)."""
    assert np.array_equal(lifted.mesh.points, phantom.mesh.points)
    skin = phantom.mesh.points[phantom.mesh.node_sets["skin"]]
    for name, seg in phantom.segments.items():
        before, after = seg.surface.points, lifted.segments[name].surface.points
        move = np.linalg.norm(after - before, axis=1)
        assert move.min() > 0 and move.max() <= 10.0 + 1e-9
        nearest = skin[np.argmin(((before[:, None] - skin[None]) ** 2).sum(-1), axis=1)]
        assert np.all(np.linalg.norm(nearest - after, axis=1) > np.linalg.norm(nearest - before, axis=1) - 1e-9)
    options = SimulationOptions(max_mucosa_offset=20.0)
    result = simulate(lifted, default_plan(lifted), 1, "linear", "mucosa", options=options)
    stats = result.summary()["mucosa_offset_mm"]
    assert 1.0 < stats["median"] < 4.0 and stats["median"] <= stats["p90"] <= stats["max"] <= 10.0


@pytest.mark.parametrize("material", ["linear", "neo-hookean"])
def test_sliding_mucosa_keeps_its_pre_operative_offset_from_the_moving_bone(lifted, material):
    """Default plan, 3 increments, every mucosa node sliding: after every increment each lies at its
    pre-operative distance from its moved bone (on the offset surface, 1e-5 mm; the rough bone
    is concave within the offset in places, where the projection is repeated), no element
    inverted; the summary's offset statistics are those of the pre-operative geometry."""
    plan = default_plan(lifted)
    result = simulate(lifted, plan, 3, material, "mucosa+lip", options=SimulationOptions(max_mucosa_offset=np.inf))
    bc = result.boundary
    mucosa = bc.nodes(NodeType.MUCOSA_SLIDING)
    X = lifted.mesh.points
    d0 = _distance_to_bone(lifted, plan.interpolated(0.0), mucosa, bc.segment, bc.segment_names, X)
    assert np.allclose(result.mucosa_offset, d0, atol=1e-12) and d0.min() > 0
    for k in range(1, 4):
        d = _distance_to_bone(lifted, plan.interpolated(k / 3), mucosa, bc.segment, bc.segment_names,
                              X + result.displacements[k])
        drift = np.abs(d - d0)
        assert drift.max() < 1e-5, k
    summary = result.summary()
    assert summary["min_scaled_jacobian"] > 0.1
    assert summary["mucosa_offset_mm"]["median"] == pytest.approx(np.median(d0), abs=1e-12)
    assert summary["mucosa_offset_mm"]["max"] == pytest.approx(d0.max(), abs=1e-12)
    assert summary["far_mucosa_nodes"] == 0


def test_mucosa_farther_than_max_mucosa_offset_is_left_free(lifted):
    """With ``max_mucosa_offset = 2`` mm the mucosa nodes farther than 2 mm from their bone are
    free (listed in the result and counted in the summary); the others still slide."""
    options = SimulationOptions(max_mucosa_offset=2.0)
    result = simulate(lifted, default_plan(lifted), 1, "linear", "mucosa", options=options)
    everyone = simulate(lifted, default_plan(lifted), 1, "linear", "mucosa",
                        options=SimulationOptions(max_mucosa_offset=np.inf))
    far = result.far_mucosa
    assert far.size == int((everyone.mucosa_offset > 2.0).sum()) > 0
    assert np.all(result.boundary.types[far] == NodeType.FREE)
    assert result.summary()["far_mucosa_nodes"] == far.size
    sliding = everyone.boundary.nodes(NodeType.MUCOSA_SLIDING)
    assert np.array_equal(result.boundary.nodes(NodeType.MUCOSA_SLIDING), np.setdiff1d(sliding, far))


def test_phantom_mucosa_lies_on_its_bone(phantom):
    """The phantom's mucosa lies exactly on its bone: every offset is zero."""
    result = simulate(phantom, default_plan(phantom), 1, "linear", "mucosa")
    assert result.summary()["mucosa_offset_mm"] == {"nodes": result.mucosa_offset.size, "median": 0.0, "p90": 0.0,
                                                    "max": 0.0}


@pytest.mark.parametrize("value", [-1.0, float("nan")])
def test_max_mucosa_offset_must_be_a_length(value):
    with pytest.raises(ValueError, match="max_mucosa_offset"):
        SimulationOptions(max_mucosa_offset=value)
