"""An impact answer is checked before it is given: finite, held nodes held, no inverted element in
any frame, no negative von Mises stress. The FE lists the values in ``summary.json`` and raises
when its answer fails them (the tiny coarse scene of conftest.py, about a second a run)."""

import json
import sys

import numpy as np
import pytest

from toolkit.common.errors import AnswerError
from toolkit.impact import simulate
from toolkit.impact.checks import FIXED_TOLERANCE_MM, answer_checks, min_scaled_jacobian_over_frames
from toolkit.impact.simulate import face_mesh, fixed_nodes

from .conftest import tiny_scene


@pytest.fixture(scope="module")
def face_and_fixed():
    scene = tiny_scene()
    face = face_mesh(scene)
    return face, fixed_nodes(scene, face)


def _fields(face, frames=3):
    """A stretch along y growing to 1 % over ``frames`` frames (the callers zero it at the held
    nodes) and a stress of 0.001 MPa everywhere."""
    X = face.points
    u = np.stack([0.01 * (k + 1) / frames * np.column_stack([np.zeros(len(X)), X[:, 1] - X[:, 1].min(),
                                                              np.zeros(len(X))]) for k in range(frames)])
    return u, np.full(u.shape[:2], 1e-3)


def test_a_sound_answer_passes_with_its_values(face_and_fixed):
    face, fixed = face_and_fixed
    u, vm = _fields(face)
    u[:, fixed] = 0.0
    checks = answer_checks(face, u, vm, fixed)
    assert checks["passed"] and checks["problems"] == []
    assert checks["held_max_displacement_mm"] == 0.0 and checks["min_von_mises_mpa"] == pytest.approx(1e-3)
    assert 0 < checks["min_scaled_jacobian"] <= 1 and checks["seconds"] >= 0


def test_each_fault_is_named(face_and_fixed):
    """An element folded through its opposite face in frame 1, a held node moved 0.1 mm, a negative
    stress and a NaN: each is one problem, with where and how much."""
    face, fixed = face_and_fixed
    u, vm = _fields(face)
    u[:, fixed] = 0.0
    cell = face.volume_cells[0]
    apex, base = cell[0], cell[1:4]
    centroid = face.points[base].mean(axis=0)
    u[1, apex] = 2.0 * (centroid - face.points[apex])  # the apex mirrored through its opposite face
    assert min_scaled_jacobian_over_frames(face, u)[0] < 0
    checks = answer_checks(face, u, vm, fixed)
    assert not checks["passed"] and checks["min_scaled_jacobian_frame"] == 1
    assert any("first inverts in frame 1" in p for p in checks["problems"])

    u2, vm2 = _fields(face)
    u2[:, fixed] = 0.0
    u2[2, fixed[0]] = [0.0, 0.1, 0.0]
    vm2[0, 5] = -1e-4
    checks = answer_checks(face, u2, vm2, fixed)
    assert checks["held_max_displacement_mm"] == pytest.approx(0.1) and 0.1 > FIXED_TOLERANCE_MM
    assert checks["min_von_mises_mpa"] == pytest.approx(-1e-4)
    assert len(checks["problems"]) == 2 and "held nodes moved up to 0.1 mm" in checks["problems"][0]
    assert "1 of" in checks["problems"][1] and "negative von Mises" in checks["problems"][1]

    vm2[:] = 1e-3
    u2[2, fixed[0]] = 0.0
    u2[0, 7, 2] = np.nan
    checks = answer_checks(face, u2, vm2, fixed)
    assert not checks["finite"] and "NaN or infinite" in checks["problems"][0]


def test_the_fe_lists_its_checks_in_the_summary(tmp_path):
    result = simulate(tiny_scene(), out=tmp_path / "o", preview=False)
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    checks = summary["checks"]["answer"]
    assert checks.keys() == result.checks.keys() and checks["passed"] and checks["problems"] == []
    assert checks["min_scaled_jacobian"] == pytest.approx(result.checks["min_scaled_jacobian"])
    assert checks["held_max_displacement_mm"] == 0.0 and checks["min_von_mises_mpa"] >= 0.0
    assert checks["min_scaled_jacobian"] > 0 and checks["seconds"] < 1.0


def test_an_fe_answer_that_fails_its_checks_is_an_error_and_marked_failed(tmp_path, monkeypatch):
    """An FE answer with an element inverted in a frame (its integrators test the integration points,
    the checks the element's corners and edges too) raises AnswerError naming the ball's travel then
    and the longest --duration whose frames passed, and summary.json says failed with the checks."""
    sim = sys.modules["toolkit.impact.simulate"]  # the module (the package exports its function)

    def failing(face, u, vm, fixed):
        checks = answer_checks(face, u, vm, fixed)
        return {**checks, "passed": False, "inverted_from_frame": 3,
                "problems": ["an element first inverts in frame 3 (stand-in)"]}

    monkeypatch.setattr(sim, "answer_checks", failing)
    with pytest.raises(AnswerError, match=r"first inverts in frame 3 .*At 0\.12 s the ball has travelled 6\.0 mm.*"
                       r"--duration \(at most 0\.0[89]\d* s at 50 mm/s"):
        simulate(tiny_scene(), out=tmp_path / "o", preview=False)
    summary = json.loads((tmp_path / "o" / "summary.json").read_text())
    assert summary["status"] == "failed" and "first inverts in frame 3" in summary["error"]
    assert summary["checks"]["answer"]["passed"] is False
