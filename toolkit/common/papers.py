"""Every number taken from the source papers, in one place (mm, s, tonne, MPa).

The modules that use them (materials, plan ranges, impact scene and plasticity) import them
from here, so a reader checks a value against its paper once.

The lip-sliding paper (orthognathic soft-tissue FEM, section 2.3): homogeneous linear soft tissue and a
transversely isotropic lip muscle; the physiological ranges of the Le Fort I and distal
mandible movements measured on its patients (section 2.3.2.2).

The impact paper (ball impact on the face): the face and rubber-ball materials with their yield
tables, a size-5 football, Coulomb friction, the ball velocities and the simulated time.
"""

from __future__ import annotations

import math

__all__ = [
    "TISSUE_E", "TISSUE_NU", "LIP_MUSCLE_E_FIBRE", "LIP_MUSCLE_E_TRANSVERSE",
    "LEFORT_TRANSLATION_MM", "LEFORT_ROTATION_DEG", "DISTAL_TRANSLATION_MM", "DISTAL_ROTATION_DEG",
    "FACE_E", "FACE_NU", "FACE_DENSITY", "FACE_YIELD", "BALL_E", "BALL_NU", "BALL_MASS", "BALL_RADIUS",
    "BALL_YIELD", "FRICTION", "BALL_VELOCITY", "BALL_VELOCITIES", "IMPACT_DURATION", "ball_density",
]

# ------------------------------------------------------------------ the lip-sliding paper
#: MPa, Young's modulus of the soft tissue (3 kPa)
TISSUE_E = 0.003
#: Poisson's ratio of every soft tissue (nearly incompressible)
TISSUE_NU = 0.47
#: MPa, lip muscle along its fibres (superior-inferior) and across them
LIP_MUSCLE_E_FIBRE = 0.009
LIP_MUSCLE_E_TRANSVERSE = 0.003
#: (lo, hi) of the Le Fort I segment's movement: pivot translation mm, rotation angle degrees
LEFORT_TRANSLATION_MM = (0.0, 6.3)
LEFORT_ROTATION_DEG = (0.0, 9.8)
#: (lo, hi) of the distal mandible's movement
DISTAL_TRANSLATION_MM = (2.1, 11.5)
DISTAL_ROTATION_DEG = (0.5, 13.3)

# ------------------------------------------------------------------ the impact paper
#: face: MPa, Poisson's ratio, tonne/mm^3 (1000 kg/m^3)
FACE_E = 0.015
FACE_NU = 0.49
FACE_DENSITY = 1e-9
#: face yield table: (yield stress MPa, equivalent plastic strain), piecewise linear
FACE_YIELD = ((0.015, 0.0), (0.020, 0.03), (0.025, 0.032), (0.028, 0.05), (0.030, 0.06), (0.031, 0.07))
#: rubber ball: MPa, Poisson's ratio
BALL_E = 0.38
BALL_NU = 0.39
#: size-5 football: tonne (0.43 kg), mm
BALL_MASS = 0.43e-3
BALL_RADIUS = 110.0
#: ball yield table: (yield stress MPa, equivalent plastic strain)
BALL_YIELD = ((0.034, 0.0), (0.035, 0.03), (0.036, 0.032), (0.037, 0.05), (0.038, 0.06), (0.039, 0.07))
#: Coulomb friction between ball and skin
FRICTION = 0.2
#: mm/s, the default ball velocity, and the impact paper's six velocities (evenly spaced over 20-50 mm/s)
BALL_VELOCITY = 30.0
BALL_VELOCITIES = (20.0, 26.0, 32.0, 38.0, 44.0, 50.0)
#: s, simulated time of an impact
IMPACT_DURATION = 1.8


def ball_density(mass: float = BALL_MASS, radius: float = BALL_RADIUS) -> float:
    """Density (tonne/mm^3) of a solid ball with the mass of a size-5 football.

    ``mass`` in tonne (0.43 kg = 0.43e-3 t), ``radius`` in mm. The real ball is a
    pressurised shell; a solid ball of this density has the right mass.
    """
    return mass / (4.0 / 3.0 * math.pi * radius**3)
