"""Every value taken from the source papers has one home: ``toolkit.common.papers`` holds them
(transcribed again here from the papers, independently), and the modules that use them read them
from there rather than keeping copies."""

import ast
import inspect

import numpy as np

from toolkit.common import papers
from toolkit.common.fem.materials import LinearElastic, NeoHookean, TransverselyIsotropic
from toolkit.common.phantoms.phantom import ball_density
from toolkit.impact import plasticity, scene
from toolkit.impact.database import PAPER_VELOCITIES
from toolkit.static.plan import PHYSIOLOGICAL_RANGES

# the impact paper's yield tables (MPa, plastic strain)
PAPER_FACE_YIELD = [(0.015, 0.0), (0.020, 0.03), (0.025, 0.032), (0.028, 0.05), (0.030, 0.06), (0.031, 0.07)]
PAPER_BALL_YIELD = [(0.034, 0.0), (0.035, 0.03), (0.036, 0.032), (0.037, 0.05), (0.038, 0.06), (0.039, 0.07)]


def test_the_values_are_those_of_the_papers():
    assert (papers.TISSUE_E, papers.TISSUE_NU) == (0.003, 0.47)
    assert (papers.LIP_MUSCLE_E_FIBRE, papers.LIP_MUSCLE_E_TRANSVERSE) == (0.009, 0.003)
    assert (papers.LEFORT_TRANSLATION_MM, papers.LEFORT_ROTATION_DEG) == ((0.0, 6.3), (0.0, 9.8))
    assert (papers.DISTAL_TRANSLATION_MM, papers.DISTAL_ROTATION_DEG) == ((2.1, 11.5), (0.5, 13.3))
    assert (papers.FACE_E, papers.FACE_NU, papers.FACE_DENSITY) == (0.015, 0.49, 1e-9)
    assert (papers.BALL_E, papers.BALL_NU, papers.FRICTION) == (0.38, 0.39, 0.2)
    np.testing.assert_array_equal(papers.FACE_YIELD, PAPER_FACE_YIELD)
    np.testing.assert_array_equal(papers.BALL_YIELD, PAPER_BALL_YIELD)
    assert len(papers.BALL_VELOCITIES) == 6 and min(papers.BALL_VELOCITIES) == 20 and max(papers.BALL_VELOCITIES) == 50
    # a solid 110 mm ball of 0.43 kg: 0.43e-3 t / (4/3 pi 110^3 mm^3)
    np.testing.assert_allclose(papers.ball_density(), 0.43e-3 / (4 / 3 * np.pi * 110.0**3), rtol=1e-15)


def test_every_user_reads_the_paper_values_from_one_place():
    assert (LinearElastic().E, LinearElastic().nu, NeoHookean().E, NeoHookean().nu) == (0.003, 0.47, 0.003, 0.47)
    t = TransverselyIsotropic()
    assert (t.E_fibre, t.E_transverse, t.nu) == (0.009, 0.003, 0.47)
    assert PHYSIOLOGICAL_RANGES["lefort"].translation_mm == papers.LEFORT_TRANSLATION_MM
    assert PHYSIOLOGICAL_RANGES["distal"].rotation_deg == papers.DISTAL_ROTATION_DEG
    assert scene.FACE_YIELD is papers.FACE_YIELD and scene.BALL_YIELD is papers.BALL_YIELD
    assert plasticity.FACE_TABLE == plasticity.HardeningTable.from_pairs(PAPER_FACE_YIELD)
    assert plasticity.BALL_TABLE == plasticity.HardeningTable.from_pairs(PAPER_BALL_YIELD)
    assert plasticity.PAPER_BALL.density == papers.ball_density() == ball_density()
    face, ball = scene.FaceSpec().material, scene.BallSpec().material
    assert (face.E, face.nu, face.density, face.yield_table) == (0.015, 0.49, 1e-9, papers.FACE_YIELD)
    assert (ball.E, ball.nu, ball.yield_table) == (0.38, 0.39, papers.BALL_YIELD)
    assert PAPER_VELOCITIES == papers.BALL_VELOCITIES and scene.Scene().duration == papers.IMPACT_DURATION


def test_plasticity_does_not_import_the_phantom_generator():
    tree = ast.parse(inspect.getsource(plasticity))
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
    imported |= {a.name for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
    assert "toolkit.common.phantoms.phantom" not in imported
