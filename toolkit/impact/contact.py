"""Penalty contact with Coulomb friction for the explicit impact solver (the impact paper).

The impact paper specifies "hard" normal contact and a penalty tangential behaviour with Coulomb
friction 0.2. Both are enforced here by penalty springs on the slave nodes (the face's skin
nodes), evaluated once per explicit time step:

* :func:`penalty_stiffness` picks the normal penalty per slave from its lumped mass and the time
  step, so that the springs do not spoil the explicit stability limit; "hard" contact is then
  approximated by a penetration of ``f_n / k`` (a small fraction of a millimetre for the impact
  paper's loads).
* :class:`CoulombFriction` is the tangential law: an elastic stick spring with a stick/slip
  return mapping (an elastic predictor and a radial return to the Coulomb cone).
* :class:`RigidSphereContact` is node-to-analytic-sphere contact (the rigid ball of radius
  110 mm moved at an imposed velocity).
* :class:`SurfaceContact` is node-to-surface contact against a deformable body's outer triangles
  (the tet10 ball's boundary faces, corner nodes only); the reaction is handed to the triangle
  nodes with the barycentric weights of the contact point, so momentum is conserved exactly.

Both contact classes hold the tangential state (the elastic friction force of every slave) and
advance it at each :meth:`step` call, so ``step`` must be called exactly once per time step.
Units: mm, s, N, tonne; energies in mJ (N mm).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from toolkit.common.analysis.surface_distance import barycentric, closest_points

__all__ = [
    "ContactStep",
    "CoulombFriction",
    "FrictionUpdate",
    "RigidSphereContact",
    "SurfaceContact",
    "orient_outward",
    "penalty_stiffness",
]


# ----------------------------------------------------------------------------------------------
# penalty stiffness
# ----------------------------------------------------------------------------------------------


def penalty_stiffness(node_mass, dt: float, fraction: float = 0.9) -> np.ndarray:
    """Normal penalty stiffness per node that keeps the explicit time step usable.

    A node of mass ``m`` held by a structural stiffness ``k_s`` has the central-difference
    critical step ``dt = 2 / sqrt(k_s / m)``, i.e. ``k_s = m (2/dt)^2`` when ``dt`` is its critical
    step (and ``k_s <= m (2/dt)^2`` whenever ``dt`` is stable). Adding a contact spring
    ``k_pen = beta m (2/dt)^2`` gives ``k_s + k_pen <= (1 + beta) m (2/dt)^2`` and hence a
    critical step of at least ``dt / sqrt(1 + beta)``. Choosing ``beta = 1/fraction^2 - 1``
    (``fraction = 0.9`` -> ``beta = 0.2346``) means the penalty does not shrink the stable time
    step below ``fraction`` of the structural one. The contact spring on its own has the critical
    step ``dt / sqrt(beta)`` (2.06 ``dt`` for ``fraction = 0.9``).

    Usage: pass the structural critical step as ``dt`` and run the solver with a Courant factor
    ``<= fraction``. If ``dt`` is instead the solver's actual step ``s * dt_crit``, the combined
    system stays stable provided ``s^2 + beta <= 1`` (``s <= 0.875`` for ``fraction = 0.9``).
    The tangential stick spring of :class:`CoulombFriction` (``stiffness_ratio <= 1``) acts in
    the directions orthogonal to the normal spring, so the same bound holds per direction. In
    node-to-surface contact the master nodes carry ``w_i^2 k`` per contact (``w_i <= 1``), so pass
    the smaller of the slave and master nodal masses when the master is lighter.

    Parameters
    ----------
    node_mass : (n,) float, tonne
        Lumped nodal masses (>= 0; a massless node gets a zero penalty, i.e. no contact).
    dt : float, s
        Structural critical time step (> 0).
    fraction : float
        Fraction of ``dt`` the combined critical step must keep, in ``(0, 1]``.

    Returns
    -------
    (n,) float, N/mm
    """
    m = np.asarray(node_mass, dtype=np.float64)
    if m.ndim != 1:
        raise ValueError(f"node_mass has shape {m.shape}, expected (n,) nodal masses in tonne")
    if not np.all(np.isfinite(m)) or np.any(m < 0):
        bad = np.flatnonzero(~np.isfinite(m) | (m < 0))
        raise ValueError(
            f"node_mass has {bad.size} negative or non-finite entries (first: node {bad[0]}, "
            f"{m[bad[0]]}); expected masses >= 0 in tonne (use a positive lumped mass, e.g. HRZ)"
        )
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt={dt}, expected a positive time step in s")
    if not (0 < fraction <= 1):
        raise ValueError(f"fraction={fraction}, expected 0 < fraction <= 1")
    beta = 1.0 / fraction**2 - 1.0
    return beta * m * (2.0 / dt) ** 2


# ----------------------------------------------------------------------------------------------
# friction law
# ----------------------------------------------------------------------------------------------


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _projected(vectors: np.ndarray, normal: np.ndarray, keep_length: bool) -> np.ndarray:
    """Rows of ``vectors`` (n, 3) with their component along the unit ``normal`` (n, 3) dropped;
    rescaled to their original length when ``keep_length`` (zero where the projection vanishes)."""
    p = vectors - _dot(vectors, normal)[:, None] * normal
    if not keep_length:
        return p
    old = np.linalg.norm(vectors, axis=1)
    new = np.linalg.norm(p, axis=1)
    ok = new > 1e-12 * old
    scale = np.divide(old, new, out=np.zeros_like(old), where=ok)
    return p * scale[:, None]


@dataclass(frozen=True, eq=False)
class FrictionUpdate:
    """Result of one friction return mapping for ``n`` contact points.

    Attributes
    ----------
    force : (n, 3) float, N — tangential force on the slave (in the current tangent plane)
    slipping : (n,) bool — True where the trial force left the Coulomb cone
    slip : (n,) float, mm — magnitude of this step's slip increment (0 where sticking)
    dissipation : (n,) float, mJ — friction work of this step, ``|force| * slip``
    energy : (n,) float, mJ — energy stored in the stick spring, ``|force|^2 / (2 k_t)``
    """

    force: np.ndarray
    slipping: np.ndarray
    slip: np.ndarray
    dissipation: np.ndarray
    energy: np.ndarray


@dataclass(frozen=True)
class CoulombFriction:
    """Coulomb friction with a penalty (elastic-stick) tangential behaviour.

    The tangential force on a slave is an elastic spring force ``t`` of stiffness
    ``k_t = stiffness_ratio * k_n`` (``k_n`` the slave's normal penalty), capped by the Coulomb
    limit ``mu |f_n|``. For a relative tangential displacement increment ``du_t`` of the slave
    with respect to the master (slave minus master), the return mapping is

    * trial: ``t_trial = t_old - k_t du_t`` (the force on the slave opposes its relative motion;
      the elastic stick displacement is ``-t / k_t``);
    * stick if ``|t_trial| <= mu |f_n|``: ``t = t_trial``;
    * slip otherwise: ``t = mu |f_n| t_trial / |t_trial|``, slip increment
      ``(|t_trial| - mu |f_n|) / k_t`` along ``-t / |t|`` and dissipation ``|t|`` times it.

    In one dimension this mapping is exact for any increment size (the stick-to-slip transition
    inside an increment is resolved by the radial return).

    Before the predictor, ``t_old`` is transported to the current tangent plane: its normal
    component is dropped and the result rescaled to the old magnitude (a rotation for small
    changes of the normal), so a rolling contact normal neither creates nor destroys stored
    friction force. ``t_old`` is zero for a node that was not in contact at the previous step.

    Parameters
    ----------
    mu : float
        Friction coefficient (>= 0), 0.2 in the impact paper.
    stiffness_ratio : float
        ``k_t / k_n`` (> 0). With ``<= 1`` the stick spring respects the same time-step bound
        as the normal penalty (see :func:`penalty_stiffness`).
    """

    mu: float = 0.2
    stiffness_ratio: float = 1.0

    def __post_init__(self):
        if not (np.isfinite(self.mu) and self.mu >= 0):
            raise ValueError(f"mu={self.mu}, expected a friction coefficient >= 0")
        if not (np.isfinite(self.stiffness_ratio) and self.stiffness_ratio > 0):
            raise ValueError(f"stiffness_ratio={self.stiffness_ratio}, expected k_t / k_n > 0")

    def return_map(self, previous, increment, normal, normal_force, normal_stiffness) -> FrictionUpdate:
        """One stick/slip return mapping for ``n`` contact points (vectorised).

        Parameters
        ----------
        previous : (n, 3) float, N
            Tangential force on the slave at the previous step (zero for new contacts).
        increment : (n, 3) float, mm
            Relative displacement increment of the slave with respect to the master over the step;
            its normal component is ignored.
        normal : (n, 3) float
            Current unit contact normals.
        normal_force : (n,) float, N
            Normal force magnitude (its absolute value is used).
        normal_stiffness : (n,) float, N/mm
            Normal penalty ``k_n``; ``k_t = stiffness_ratio * k_n``.

        Returns
        -------
        FrictionUpdate
        """
        n = np.asarray(normal, dtype=np.float64)
        t_old = _projected(np.asarray(previous, dtype=np.float64), n, keep_length=True)
        du_t = _projected(np.asarray(increment, dtype=np.float64), n, keep_length=False)
        k_t = self.stiffness_ratio * np.asarray(normal_stiffness, dtype=np.float64)
        trial = t_old - k_t[:, None] * du_t
        size = np.linalg.norm(trial, axis=1)
        limit = self.mu * np.abs(np.asarray(normal_force, dtype=np.float64))
        slipping = size > limit
        scale = np.divide(limit, size, out=np.ones_like(size), where=slipping)
        force = trial * scale[:, None]
        has_spring = k_t > 0
        slip = np.divide(size - limit, k_t, out=np.zeros_like(size), where=slipping & has_spring)
        dissipation = np.where(slipping, limit, 0.0) * slip
        energy = np.divide(np.einsum("ij,ij->i", force, force), 2.0 * k_t, out=np.zeros_like(size), where=has_spring)
        return FrictionUpdate(force, slipping, slip, dissipation, energy)


# ----------------------------------------------------------------------------------------------
# contact results and shared state handling
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ContactStep:
    """Contact response for one explicit time step.

    Attributes
    ----------
    force : (n_slave, 3) float, N
        Contact force on each slave node (normal penalty plus friction); add it to the slave
        rows of the nodal force vector.
    normal_force_total : (3,) float, N
        Force the slaves' normal springs exert on the master (the ball): minus the sum of the
        normal parts of ``force``.
    master_force_total : (3,) float, N
        Total force the slaves exert on the master, friction included: ``-force.sum(axis=0)``.
    penetration : (n_slave,) float, mm
        Penetration depth ``max(-gap, 0)`` of the active slaves, 0 elsewhere.
    active : (n_slave,) bool
    n_active : int
    n_candidates : int
        Slaves that passed the cheap bounding test (0 when the bodies are apart).
    elastic_energy : float, mJ
        Energy stored in the penalty springs now: ``sum k g^2 / 2`` plus the stick springs'
        ``sum |t|^2 / (2 k_t)``.
    friction_dissipation : float, mJ
        Friction work dissipated during this step (>= 0).
    tangential_force : (n_slave, 3) float, N
        Friction part of ``force``.
    slipping : (n_slave,) bool
        Active slaves whose friction force sits on the Coulomb limit.
    master_force : (n_nodes, 3) float, N, or None
        :class:`SurfaceContact` only: reaction on every mesh node (non-zero on the master
        triangles' nodes), ``force`` distributed with the contact point's barycentric weights
        and reversed; ``force.sum(0) + master_force.sum(0) == 0`` to round-off.
    normal : (n_slave, 3) float or None
        Unit contact normal of the active slaves (zero rows elsewhere); what a quasi-static
        solver linearises the penalty force with.
    corners : (n_slave, 3) int or None
        :class:`SurfaceContact` only: the master triangle's node ids of each active slave.
    weights : (n_slave, 3) float or None
        :class:`SurfaceContact` only: the barycentric weights of the contact point on it.
    slip : (n_slave,) float, mm, or None
        This step's slip increment of each slipping slave (0 where sticking or apart).
    """

    force: np.ndarray
    normal_force_total: np.ndarray
    master_force_total: np.ndarray
    penetration: np.ndarray
    active: np.ndarray
    n_active: int
    n_candidates: int
    elastic_energy: float
    friction_dissipation: float
    tangential_force: np.ndarray
    slipping: np.ndarray
    master_force: np.ndarray | None = None
    normal: np.ndarray | None = None
    corners: np.ndarray | None = None
    weights: np.ndarray | None = None
    slip: np.ndarray | None = None


def _as_index_array(a, name: str) -> np.ndarray:
    arr = np.asarray(a)
    if arr.ndim != 1 or arr.size == 0 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} has shape {arr.shape} and dtype {arr.dtype}, expected (n,) int node ids, n >= 1")
    if arr.min() < 0:
        raise ValueError(f"{name} holds negative node ids (min {arr.min()}); expected ids >= 0")
    if np.unique(arr).size != arr.size:
        raise ValueError(f"{name} holds {arr.size - np.unique(arr).size} repeated node ids; expected unique ids")
    return arr.astype(np.int64)


class _PenaltyContact:
    """Slave set, penalties, friction law and the tangential state shared by both contacts."""

    def __init__(self, slaves, penalty, friction: CoulombFriction | None):
        self.slaves = _as_index_array(slaves, "slaves")
        n = self.slaves.size
        k = np.asarray(penalty, dtype=np.float64)
        if k.ndim == 0:
            k = np.full(n, float(k))
        if k.shape != (n,):
            raise ValueError(f"penalty has shape {k.shape}, expected ({n},) (one stiffness per slave) or a scalar")
        if not np.all(np.isfinite(k)) or np.any(k < 0):
            raise ValueError(f"penalty has negative or non-finite entries (min {k.min()}); expected N/mm >= 0")
        self.penalty = k
        if friction is not None and not isinstance(friction, CoulombFriction):
            raise ValueError(f"friction is a {type(friction).__name__}, expected CoulombFriction or None")
        self.friction = friction
        self._traction = np.zeros((n, 3))

    @property
    def n_slaves(self) -> int:
        return self.slaves.size

    @property
    def tangential_state(self) -> np.ndarray:
        """(n_slave, 3) float, N: the stored elastic friction force (a copy)."""
        return self._traction.copy()

    def reset(self) -> None:
        """Forget the tangential state (all slaves start the next step out of contact)."""
        self._traction[:] = 0.0

    def restore(self, tangential_state: np.ndarray) -> None:
        """Set the stored friction force ``(n_slave, 3)`` N, e.g. back to a converged step's
        :attr:`tangential_state` before the quasi-static solver evaluates another trial state."""
        self._traction[:] = self._check_slave_points(tangential_state, "tangential_state")

    def _check_slave_points(self, a, name: str) -> np.ndarray:
        arr = np.asarray(a, dtype=np.float64)
        if arr.shape != (self.n_slaves, 3):
            raise ValueError(f"{name} has shape {arr.shape}, expected ({self.n_slaves}, 3) (one row per slave)")
        return arr

    def _empty(self, n_candidates: int, n_nodes: int | None) -> ContactStep:
        self._traction[:] = 0.0
        n = self.n_slaves
        return ContactStep(
            force=np.zeros((n, 3)),
            normal_force_total=np.zeros(3),
            master_force_total=np.zeros(3),
            penetration=np.zeros(n),
            active=np.zeros(n, dtype=bool),
            n_active=0,
            n_candidates=n_candidates,
            elastic_energy=0.0,
            friction_dissipation=0.0,
            tangential_force=np.zeros((n, 3)),
            slipping=np.zeros(n, dtype=bool),
            master_force=None if n_nodes is None else np.zeros((n_nodes, 3)),
            normal=np.zeros((n, 3)),
        )

    def _respond(self, ids, normal, gap, increment, n_candidates):
        """Forces of the active slaves ``ids`` (local slave indices) and the state update.

        normal : (a, 3) unit outward normals of the master; gap : (a,) < 0, mm; increment : (a, 3)
        relative displacement increment, mm. Returns the ContactStep fields for the full slave set
        and the (a, 3) force on the active slaves.
        """
        n = self.n_slaves
        k = self.penalty[ids]
        fn = -k * gap  # >= 0, N
        f_normal = fn[:, None] * normal
        tangential = np.zeros((n, 3))
        slipping = np.zeros(n, dtype=bool)
        slip = np.zeros(n)
        energy = 0.5 * float(np.dot(k, gap * gap))
        dissipation = 0.0
        previous = self._traction[ids]
        self._traction[:] = 0.0  # slaves that left contact forget their friction force
        if self.friction is not None:
            upd = self.friction.return_map(previous, increment, normal, fn, k)
            self._traction[ids] = upd.force
            tangential[ids] = upd.force
            slipping[ids] = upd.slipping
            slip[ids] = upd.slip
            energy += float(upd.energy.sum())
            dissipation = float(upd.dissipation.sum())
        f_active = f_normal + tangential[ids]
        force = np.zeros((n, 3))
        force[ids] = f_active
        penetration = np.zeros(n)
        penetration[ids] = -gap
        active = np.zeros(n, dtype=bool)
        active[ids] = True
        normals = np.zeros((n, 3))
        normals[ids] = normal
        fields = {
            "normal": normals,
            "slip": slip,
            "force": force,
            "normal_force_total": -f_normal.sum(axis=0),
            "master_force_total": -f_active.sum(axis=0),
            "penetration": penetration,
            "active": active,
            "n_active": int(ids.size),
            "n_candidates": int(n_candidates),
            "elastic_energy": energy,
            "friction_dissipation": dissipation,
            "tangential_force": tangential,
            "slipping": slipping,
        }
        return fields, f_active


# ----------------------------------------------------------------------------------------------
# rigid analytic sphere
# ----------------------------------------------------------------------------------------------


class RigidSphereContact(_PenaltyContact):
    """Slave nodes against a rigid analytic sphere moved at an imposed velocity.

    Gap ``g = |x - c| - R``; a slave is active when ``g < 0`` and then receives the normal force
    ``-k g`` along the sphere's outward normal ``(x - c)/|x - c|`` plus the Coulomb friction of
    :class:`CoulombFriction`. The ball translates without spinning (the impact paper drives it at a
    uniform velocity), so the relative velocity at the contact point is
    ``v_slave - centre_velocity`` and the relative displacement increment is its tangential
    part times ``dt``.

    Search: no contact search for pairs that cannot touch. The slaves' bounding box is tested
    against the sphere inflated by ``margin`` first (O(n_slave) min/max, everything skipped when
    it misses); then only slaves within ``R + margin`` of the centre get their gap evaluated.
    Any ``margin >= 0`` gives the same forces; a positive one only widens ``n_candidates``.

    Parameters
    ----------
    radius : float, mm
        Sphere radius (110 mm in the impact paper).
    penalty : (n_slave,) float, N/mm, or a scalar
        Normal penalty per slave, typically :func:`penalty_stiffness` of the slaves' masses.
    friction : CoulombFriction or None
        None for frictionless contact.
    slaves : (n_slave,) int
        Node ids of the slaves (kept for the caller's gather/scatter; :meth:`step` takes the
        slave rows only).
    margin : float, mm
        Inflation of the sphere for the bounding test (>= 0).
    """

    def __init__(self, radius: float, penalty, friction: CoulombFriction | None, slaves, *, margin: float = 0.0):
        if not (np.isfinite(radius) and radius > 0):
            raise ValueError(f"radius={radius}, expected a positive sphere radius in mm")
        if not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"margin={margin}, expected a search margin >= 0 in mm")
        super().__init__(slaves, penalty, friction)
        self.radius = float(radius)
        self.margin = float(margin)

    def step(self, x_slave, v_slave, centre, centre_velocity, dt: float) -> ContactStep:
        """Contact forces for the current configuration; advances the friction state.

        Parameters
        ----------
        x_slave : (n_slave, 3) float, mm
            Current slave positions (central difference: ``x^n``).
        v_slave : (n_slave, 3) float, mm/s
            Velocity that moved the slaves over the last step (central difference:
            ``v^{n-1/2}``), so ``v dt`` is the displacement increment since the previous call.
        centre : (3,) float, mm
            Current sphere centre.
        centre_velocity : (3,) float, mm/s
            Sphere velocity over the last step.
        dt : float, s
            Time step.

        Returns
        -------
        ContactStep (``master_force`` is None; the force on the ball is ``master_force_total``).
        """
        x = self._check_slave_points(x_slave, "x_slave")
        c = np.asarray(centre, dtype=np.float64).reshape(3)
        reach = self.radius + self.margin
        lo, hi = x.min(axis=0), x.max(axis=0)
        outside = np.maximum(np.maximum(lo - c, c - hi), 0.0)
        if float(np.dot(outside, outside)) >= reach * reach:
            return self._empty(0, None)
        d = x - c
        r2 = _dot(d, d)
        cand = np.flatnonzero(r2 < reach * reach)
        if cand.size == 0:
            return self._empty(0, None)
        r = np.sqrt(r2[cand])
        gap = r - self.radius
        inside = gap < 0
        ids, r, gap = cand[inside], r[inside], gap[inside]
        if ids.size == 0:
            return self._empty(int(cand.size), None)
        safe = np.where(r > 0, r, 1.0)
        normal = d[ids] / safe[:, None]
        normal[r == 0] = (0.0, 0.0, 1.0)  # a slave exactly at the centre: any direction
        if self.friction is not None:
            v = self._check_slave_points(v_slave, "v_slave")
            increment = (v[ids] - np.asarray(centre_velocity, dtype=np.float64).reshape(3)) * dt
        else:
            increment = np.zeros((ids.size, 3))
        fields, _ = self._respond(ids, normal, gap, increment, cand.size)
        return ContactStep(**fields)


# ----------------------------------------------------------------------------------------------
# deformable master surface
# ----------------------------------------------------------------------------------------------


def orient_outward(triangles, points, inside_point) -> np.ndarray:
    """Triangles re-wound so that their normals point away from ``inside_point``.

    A triangle ``(a, b, c)`` has the normal ``(b - a) x (c - a)``; it is flipped to ``(a, c, b)``
    when that normal points towards ``inside_point`` (seen from its centroid). Exact for
    surfaces that are star-shaped about ``inside_point`` (a ball and its centre); boundary faces
    from :func:`toolkit.common.meshes.topology.boundary_faces` of positively oriented cells are already
    outward and need no fixing.

    Parameters
    ----------
    triangles : (m, 3) int
    points : (n_nodes, 3) float, mm
    inside_point : (3,) float, mm

    Returns
    -------
    (m, 3) int64, a new array.
    """
    t = np.array(triangles, dtype=np.int64)
    p = np.asarray(points, dtype=np.float64)
    if t.ndim != 2 or t.shape[1] != 3:
        raise ValueError(f"triangles has shape {t.shape}, expected (m, 3)")
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"points has shape {p.shape}, expected (n_nodes, 3)")
    a, b, c = p[t[:, 0]], p[t[:, 1]], p[t[:, 2]]
    normal = np.cross(b - a, c - a)
    outward = (a + b + c) / 3.0 - np.asarray(inside_point, dtype=np.float64).reshape(3)
    flip = _dot(normal, outward) < 0
    t[flip] = t[flip][:, [0, 2, 1]]
    return t


def _contact_weights(p, a, b, c) -> np.ndarray:
    """Barycentric weights (n, 3) of points ``p`` on triangles ``(a, b, c)``
    (:func:`~toolkit.common.analysis.surface_distance.barycentric`), clipped to >= 0 and normalised to
    sum to 1 (the points lie on the triangles up to round-off)."""
    weights = np.clip(barycentric(p, np.stack([a, b, c], axis=1)), 0.0, None)
    return weights / weights.sum(axis=1, keepdims=True)


class SurfaceContact(_PenaltyContact):
    """Slave nodes against the outer triangles of a deformable body (node-to-surface penalty).

    Orientation: ``master_triangles`` must be wound counter-clockwise seen from outside the master
    body, i.e. ``(b - a) x (c - a)`` points out of it (what
    :func:`toolkit.common.meshes.topology.boundary_faces` returns for positively oriented tets; use
    :func:`orient_outward` otherwise). For a tet10 ball pass the corner nodes of its boundary faces.

    Per call: the closest point ``p`` of every candidate slave ``x`` on the master surface (exact
    among the ``k`` triangles with the nearest centroids, :func:`closest_points`) gives the gap
    ``g = (x - p) . n`` with ``n`` the unit normal of that triangle. A slave is active when it is
    behind the surface, ``g < 0``, and not deeper than ``search_fraction * h``, where ``h`` is the
    mean edge length of that triangle: nodes far behind a face (e.g. near the opposite side of a
    thin master) are not captured. An active slave receives ``-k g n`` plus Coulomb friction
    driven by its velocity relative to the contact point, ``v_slave - sum_i w_i v_i`` (``w_i`` the
    barycentric weights of ``p``); the master nodes receive ``-w_i`` times the slave force, so the
    forces balance exactly and have no moment about ``p``.

    Search: a cheap rejection first, keeping only slaves inside the master's current bounding box
    inflated by ``margin`` (default: the largest search depth ``search_fraction * max h``, so an
    open master surface still finds slaves behind it); nothing else is computed when none are.
    Otherwise a cKDTree of the current triangle centroids is rebuilt at every call (O(m log m))
    and queried for the candidates only, so the search never lags the deformation.

    Parameters
    ----------
    slaves : (n_slave,) int
        Node ids of the slave nodes (must not be master triangle nodes).
    master_triangles : (m, 3) int
        Node ids of the master surface triangles, outward oriented.
    penalty : (n_slave,) float, N/mm, or a scalar
    friction : CoulombFriction or None
    search_fraction : float
        Maximum penetration depth, as a fraction of the local element size, at which a slave is
        still captured (> 0).
    margin : float or None, mm
        Inflation of the master's bounding box for the rejection test.
    k : int
        Candidate triangles per slave for the closest-point search.
    """

    def __init__(
        self,
        slaves,
        master_triangles,
        penalty,
        friction: CoulombFriction | None = None,
        *,
        search_fraction: float = 0.5,
        margin: float | None = None,
        k: int = 8,
    ):
        super().__init__(slaves, penalty, friction)
        tri = np.asarray(master_triangles)
        if tri.ndim != 2 or tri.shape[1] != 3 or tri.shape[0] == 0 or not np.issubdtype(tri.dtype, np.integer):
            raise ValueError(
                f"master_triangles has shape {tri.shape} and dtype {tri.dtype}, expected (m, 3) int node ids, m >= 1"
            )
        if tri.min() < 0:
            raise ValueError(f"master_triangles holds negative node ids (min {tri.min()})")
        self.master_triangles = tri.astype(np.int64)
        self.master_nodes = np.unique(self.master_triangles)
        shared = np.intersect1d(self.slaves, self.master_nodes)
        if shared.size:
            raise ValueError(
                f"{shared.size} slave nodes are also master triangle nodes (first: {shared[:5]}); "
                "a node cannot contact its own surface"
            )
        if not (np.isfinite(search_fraction) and search_fraction > 0):
            raise ValueError(f"search_fraction={search_fraction}, expected > 0")
        if margin is not None and not (np.isfinite(margin) and margin >= 0):
            raise ValueError(f"margin={margin}, expected None or a bounding-box margin >= 0 in mm")
        if int(k) < 1:
            raise ValueError(f"k={k}, expected a positive number of candidate triangles")
        self.search_fraction = float(search_fraction)
        self.margin = margin
        self.k = int(k)
        self._max_id = int(max(self.slaves.max(), self.master_nodes.max()))

    def step(self, x, v, dt: float) -> ContactStep:
        """Contact forces for the current configuration; advances the friction state.

        Parameters
        ----------
        x : (n_nodes, 3) float, mm
            Current positions of all nodes (central difference: ``x^n``).
        v : (n_nodes, 3) float, mm/s
            Velocities that moved the nodes over the last step (``v^{n-1/2}``).
        dt : float, s

        Returns
        -------
        ContactStep with ``master_force`` (n_nodes, 3).
        """
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] <= self._max_id:
            raise ValueError(
                f"x has shape {x.shape}, expected (n_nodes, 3) with n_nodes > {self._max_id} (largest node id used)"
            )
        n_nodes = x.shape[0]
        tri = self.master_triangles
        a, b, c = x[tri[:, 0]], x[tri[:, 1]], x[tri[:, 2]]
        h = (np.linalg.norm(b - a, axis=1) + np.linalg.norm(c - b, axis=1) + np.linalg.norm(a - c, axis=1)) / 3.0
        margin = self.search_fraction * float(h.max()) if self.margin is None else self.margin
        xm = x[self.master_nodes]
        lo, hi = xm.min(axis=0) - margin, xm.max(axis=0) + margin
        xs = x[self.slaves]
        cand = np.flatnonzero(np.all((xs >= lo) & (xs <= hi), axis=1))
        if cand.size == 0:
            return self._empty(0, n_nodes)
        tree = cKDTree((a + b + c) / 3.0)
        cp = closest_points(xs[cand], x, tri, k=self.k, tree=tree)
        gap = _dot(xs[cand] - cp.point, cp.normal)
        hit = (gap < 0) & (-gap <= self.search_fraction * h[cp.triangle])
        if not np.any(hit):
            return self._empty(int(cand.size), n_nodes)
        ids = cand[hit]
        gap = gap[hit]
        normal = cp.normal[hit]
        t_hit = cp.triangle[hit]
        corners = tri[t_hit]  # (n_a, 3) master node ids
        weights = _contact_weights(cp.point[hit], a[t_hit], b[t_hit], c[t_hit])
        if self.friction is not None:
            v = np.asarray(v, dtype=np.float64)
            if v.shape != x.shape:
                raise ValueError(f"v has shape {v.shape}, expected the shape of x {x.shape}")
            v_point = np.einsum("ac,aci->ai", weights, v[corners])
            increment = (v[self.slaves[ids]] - v_point) * dt
        else:
            increment = np.zeros((ids.size, 3))
        fields, f_active = self._respond(ids, normal, gap, increment, cand.size)
        # reaction: -w_i f on the triangle corners; the last corner takes the remainder so the
        # three parts sum to -f (equal and opposite to round-off)
        part = -weights[:, :, None] * f_active[:, None, :]
        part[:, 2] = -f_active - part[:, 0] - part[:, 1]
        flat_ids = corners.ravel()
        flat = part.reshape(-1, 3)
        master_force = np.stack(
            [np.bincount(flat_ids, weights=flat[:, i], minlength=n_nodes) for i in range(3)], axis=1
        )
        full_corners, full_weights = np.zeros((self.n_slaves, 3), np.int64), np.zeros((self.n_slaves, 3))
        full_corners[ids], full_weights[ids] = corners, weights
        return ContactStep(**fields, master_force=master_force, corners=full_corners, weights=full_weights)
