"""Checks of a static answer: the plan against the face before any solve, the answer against the
plan before it is given.

**Before** (:func:`check_plan`, raises :class:`~toolkit.static.plan.PlanError`):

- every segment the plan moves carries tissue: its attached node set (``maxilla`` for the Le Fort
  I segment, ``mandible`` for the distal mandible) is not empty and covers at least
  ``min_carried_mm2`` of the tissue's boundary (:data:`MIN_CARRIED_MM2`) and at least
  ``min_carried_share`` of the tissue lying on its bone (its attached and sliding sets;
  :data:`MIN_CARRIED_SHARE`). A face whose labels gave
  a moving segment no tissue would move nothing and look like an answer;
- a rotating segment's pivot lies within :data:`PIVOT_REACH_MM` of its bone: a pivot far from the
  bone turns a small angle into a large translation (2 degrees about a pivot 10 m away move the
  bone 350 mm) that the plan's parameter ranges do not see;
- the motion the plan gives every point of the segment's bone (and its pivot) stays within
  :func:`reach_bound`: the parameter ranges, read as a distance at the bone's own size.

**After** (:func:`check_answer`, raises :class:`AnswerError`):

- the nodes attached to each segment follow its rigid motion (to :data:`ATTACHED_TOLERANCE_MM`);
- a plan that moves a segment by 1 mm or more moves the skin by at least :data:`SKIN_RESPONSE` of
  that motion (a zero-motion answer to a nonzero plan is an error);
- no element is inverted (minimum scaled Jacobian above zero).

Each returns the values it checked, which the result's ``summary()["checks"]`` lists.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from toolkit.common.defaults import MIN_CARRIED_MM2, MIN_CARRIED_SHARE
from toolkit.common.errors import AnswerError
from toolkit.common.meshes.mesh import Mesh
from toolkit.common.meshes.topology import lumped_boundary_area
from toolkit.static.boundary import NodeType
from toolkit.static.plan import PHYSIOLOGICAL_RANGES, PlanError, SurgicalPlan

__all__ = ["AnswerError", "check_plan", "check_answer", "answer_checks", "with_answer_checks", "carried_area",
           "reach_bound", "MIN_CARRIED_MM2", "MIN_CARRIED_SHARE",
           "PIVOT_REACH_MM", "ATTACHED_TOLERANCE_MM", "SKIN_RESPONSE", "MOVING_MM"]

#: mm, the farthest a rotating segment's pivot may lie from its bone. The farthest anatomical pivot
#: is the distal mandible's: the middle of the intercondylar axis, 56 mm from the distal segment
#: on the phantoms (half the intercondylar width, about 50 mm, on an adult); twice that
PIVOT_REACH_MM = 100.0
#: mm, how closely attached nodes must follow their segment's rigid motion
ATTACHED_TOLERANCE_MM = 1e-6
#: the least share of a segment's largest planned motion that the skin must move
SKIN_RESPONSE = 0.1
#: mm, a segment moving at least this far somewhere moves the skin
MOVING_MM = 1.0


def carried_area(mesh: Mesh, nodes: np.ndarray) -> float:
    """Boundary area (mm^2) held by ``nodes`` (int ids): the sum of their lumped boundary areas
    (:func:`~toolkit.common.meshes.topology.lumped_boundary_area`)."""

    return float(lumped_boundary_area(mesh.points, mesh.cells)[np.asarray(nodes, dtype=np.int64)].sum())


def reach_bound(name: str, bone: np.ndarray) -> float:
    """The largest motion (mm) a plan may give a point of segment ``name``'s bone ``(k, 3)`` mm:
    twice (the refusal factor of the parameter ranges) the top translation plus the top rotation
    over the bone's radius and the farthest pivot, ``2 (t + theta (r + PIVOT_REACH_MM))``."""
    r = PHYSIOLOGICAL_RANGES[name]
    radius = float(np.linalg.norm(bone - bone.mean(axis=0), axis=1).max())
    return 2.0 * (r.translation_mm[1] + np.radians(r.rotation_deg[1]) * (radius + PIVOT_REACH_MM))


def _moved(plan: SurgicalPlan, name: str, points: np.ndarray) -> np.ndarray:
    return np.linalg.norm(plan.motion(name).apply(points) - points, axis=1)


def check_plan(mesh: Mesh, bc, segments: Mapping, plan: SurgicalPlan,
               min_carried_mm2: float = MIN_CARRIED_MM2, min_carried_share: float = MIN_CARRIED_SHARE) -> dict:
    """Check ``plan`` against the face it moves (see the module); ``bc`` is the face's
    :class:`~toolkit.static.boundary.BoundaryConditions` as read from its node sets. Returns
    ``{segment: {"reach_mm", "reach_bound_mm", "pivot_to_bone_mm", "attached_nodes",
    "attached_area_mm2", "carried_share"}}`` for every segment the plan moves."""

    out = {}
    area = None  # lumped boundary area of every node, mm^2, once a moving segment needs it
    for name in bc.segment_names:
        if name not in PHYSIOLOGICAL_RANGES or name not in segments:
            continue
        motion = plan.motion(name)
        bone = segments[name].surface.points
        reach = float(np.max(_moved(plan, name, np.vstack([bone, motion.pivot[None]]))))
        if reach <= 1e-9:
            continue
        row = {"reach_mm": reach, "reach_bound_mm": float(reach_bound(name, bone))}
        if motion.angle_deg > 1e-9:
            d = float(np.linalg.norm(bone - motion.pivot, axis=1).min())
            row["pivot_to_bone_mm"] = d
            if d > PIVOT_REACH_MM:
                raise PlanError(f"{name}: pivot_mm {np.round(motion.pivot, 1).tolist()} lies {d:.0f} mm from the "
                                f"segment's bone; expected within {PIVOT_REACH_MM:g} mm (the farthest anatomical "
                                "pivot, the middle of the intercondylar axis, lies about 56 mm from the distal "
                                "segment): check the plan's pivot_mm and its units and axes")
        if reach > row["reach_bound_mm"]:
            raise PlanError(f"{name}: the plan moves a point of its bone {reach:.1f} mm; expected at most "
                            f"{row['reach_bound_mm']:.1f} mm (twice the physiological translation plus rotation at "
                            "this bone's size): check the plan's translation_mm, rotation and pivot_mm")
        if name in ("lefort", "distal"):
            attached = bc.segment_nodes(NodeType.MOVING, name)
            facing = np.union1d(attached, bc.segment_nodes(NodeType.MUCOSA_SLIDING, name))
            if area is None:
                area = lumped_boundary_area(mesh.points, mesh.cells)
            held = float(area[attached].sum())
            share = held / float(area[facing].sum()) if attached.size else 0.0
            row.update(attached_nodes=int(attached.size), attached_area_mm2=held, carried_share=share)
            if not attached.size or held < min_carried_mm2 or share < min_carried_share:
                carried = {"lefort": "maxilla", "distal": "mandible"}[name]
                raise PlanError(
                    f"the plan moves {name} by up to {reach:.1f} mm, but the face's {carried!r} set, the tissue "
                    f"that segment carries, has {attached.size} nodes covering {held:.1f} mm^2, a share of "
                    f"{share:.3f} of the tissue on its bone (with its sliding mucosa); expected at least "
                    f"{min_carried_mm2:g} mm^2 and a share of {min_carried_share:g}. The answer would leave the "
                    f"tissue behind. Relabel the face (toolkit mesh; its labels.json reports what each segment "
                    f"carries, and --rules key segments.{name}.attach chooses which tissue it carries) or give the "
                    f"mesh a {carried!r} set")
        out[name] = row
    return out


def answer_checks(mesh: Mesh, bc, plan: SurgicalPlan, displacement: np.ndarray, min_scaled_jacobian: float) -> dict:
    """The checks of a final ``displacement`` ``(n, 3)`` mm against ``plan`` on the pre-operative
    ``mesh`` with boundary conditions ``bc`` (the ones the answer was made with), without raising:
    the values checked (mm, s), ``passed`` and ``problems`` (one sentence each)."""

    t0 = time.perf_counter()
    X, u = mesh.points, np.asarray(displacement, dtype=float)
    follow, planned = 0.0, 0.0
    for name in bc.segment_names:
        if name not in PHYSIOLOGICAL_RANGES:
            continue
        nodes = bc.segment_nodes(NodeType.MOVING, name)
        if not nodes.size:
            continue
        target = plan.motion(name).apply(X[nodes]) - X[nodes]
        follow = max(follow, float(np.linalg.norm(u[nodes] - target, axis=1).max()))
        planned = max(planned, float(np.linalg.norm(target, axis=1).max()))
    skin = mesh.node_sets.get("skin")
    skin_max = float(np.linalg.norm(u[skin], axis=1).max()) if skin is not None and skin.size else None
    checks = {"attached_follow_mm": follow, "attached_tolerance_mm": ATTACHED_TOLERANCE_MM,
              "planned_attached_motion_mm": planned, "skin_max_displacement_mm": skin_max,
              "min_scaled_jacobian": float(min_scaled_jacobian)}
    problems = []
    if follow > ATTACHED_TOLERANCE_MM:
        problems.append(f"attached nodes are {follow:.3g} mm from where their segment's motion puts them "
                        f"(expected within {ATTACHED_TOLERANCE_MM:g} mm)")
    if planned >= MOVING_MM and skin_max is not None and skin_max < SKIN_RESPONSE * planned:
        problems.append(f"the plan moves attached tissue up to {planned:.2f} mm but the skin moved at most "
                        f"{skin_max:.3f} mm (expected at least {SKIN_RESPONSE:g} of it)")
    if not min_scaled_jacobian > 0:
        problems.append(f"an element is inverted (minimum scaled Jacobian {min_scaled_jacobian:.3g}; expected > 0)")
    checks.update(seconds=time.perf_counter() - t0, passed=not problems, problems=problems)
    return checks


def check_answer(mesh: Mesh, bc, plan: SurgicalPlan, displacement: np.ndarray, min_scaled_jacobian: float) -> dict:
    """:func:`answer_checks`, raising :class:`AnswerError` when one fails; returns the values checked."""
    checks = answer_checks(mesh, bc, plan, displacement, min_scaled_jacobian)
    if not checks["passed"]:
        raise AnswerError("the answer failed its checks: " + "; ".join(checks["problems"]), checks)
    return checks


def with_answer_checks(result, plan: SurgicalPlan):
    """``result`` (a :class:`~toolkit.static.simulate.SimulationResult`, e.g. a surrogate's
    prediction) with ``checks["answer"]``: its :func:`answer_checks` against ``plan``, which does not
    raise (a surrogate answer that fails is flagged, and ``predict --tolerance`` runs the FE), and
    with ``plan`` (written beside it)."""
    from dataclasses import replace

    checks = answer_checks(result.reference, result.boundary, plan, result.displacement,
                           min(r.min_scaled_jacobian for r in result.reports))
    return replace(result, checks={**(result.checks or {}), "answer": checks}, plan=plan)
