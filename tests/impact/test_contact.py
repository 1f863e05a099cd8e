"""Tests for toolkit.impact.contact: penalty stiffness, Coulomb stick/slip, sphere and surface contact.

Every expected value is a closed form (spring forces, Coulomb limits, loop areas, the
central-difference response of a spring-mass), never a number the code itself produced.
"""

import numpy as np
import pytest

import toolkit.impact.contact as contact_module
from toolkit.impact.contact import (
    CoulombFriction,
    RigidSphereContact,
    SurfaceContact,
    orient_outward,
    penalty_stiffness,
)

# ----------------------------------------------------------------------------------------------
# helpers
# ----------------------------------------------------------------------------------------------


def _unit(rng, n):
    d = rng.normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def _square():
    """Flat master square [0, 10]^2 at z = 0, two triangles with normal +z (master body below)."""
    points = np.array([[0.0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0]])
    triangles = np.array([[0, 1, 2], [0, 2, 3]])
    return points, triangles


def _octahedron(radius=10.0):
    points = radius * np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
    triangles = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])
    return points, triangles


def _block_on_sphere(tangential_load, n_steps=300):
    """Central-difference run of one node of mass m pressed by W onto the top of a (nearly flat)
    rigid sphere and pulled tangentially (+x) by T; returns the history and the parameters."""
    m, dt, W, mu, R = 1e-6, 1e-4, 1.0, 0.2, 1e8  # tonne, s, N, -, mm
    k = penalty_stiffness(np.array([m]), dt)[0]
    contact = RigidSphereContact(R, k, CoulombFriction(mu=mu), slaves=np.array([0]))
    centre = np.array([0.0, 0.0, -R])
    f_ext = np.array([tangential_load, 0.0, -W])
    x = np.array([0.0, 0.0, -W / k])  # static normal equilibrium: k * depth = W
    v = np.zeros(3)  # v^{-1/2}
    xs, vs, slipping, friction = [], [], [], []
    for _ in range(n_steps):
        res = contact.step(x[None], v[None], centre, np.zeros(3), dt)
        a = (f_ext + res.force[0]) / m
        v = v + a * dt
        x = x + v * dt
        xs.append(x.copy())
        vs.append(v.copy())
        slipping.append(bool(res.slipping[0]))
        friction.append((res.tangential_force[0].copy(), k * res.penetration[0]))
    history = {"x": np.array(xs), "v": np.array(vs), "slipping": np.array(slipping), "friction": friction}
    return {**history, "m": m, "dt": dt, "W": W, "mu": mu, "k": k}


# ----------------------------------------------------------------------------------------------
# penalty stiffness
# ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fraction", [0.9, 0.75, 1.0])
def test_penalty_keeps_fraction_of_critical_step(fraction):
    """A mass m on a critical structural spring k_s = m (2/dt)^2 plus the penalty spring has the
    central-difference critical step 2/sqrt((k_s + k_pen)/m) >= fraction * dt (equality by
    construction, to 1e-12); fraction 0.9 gives beta = 1/0.81 - 1 = 0.2346."""
    rng = np.random.default_rng(0)
    m = rng.uniform(1e-9, 1e-6, size=50)
    dt = 3.7e-5
    k_struct = m * (2 / dt) ** 2
    k_pen = penalty_stiffness(m, dt, fraction)
    dt_new = 2 / np.sqrt((k_struct + k_pen) / m)
    assert np.all(dt_new >= fraction * dt * (1 - 1e-12))
    np.testing.assert_allclose(dt_new, fraction * dt, rtol=1e-12)
    if fraction == 0.9:
        np.testing.assert_allclose(k_pen / k_struct, 1 / 0.81 - 1, rtol=1e-12)
        assert k_pen[0] / k_struct[0] == pytest.approx(0.2346, abs=1e-4)


def test_penalty_rejects_bad_input():
    """Negative masses, a non-positive dt and a fraction outside (0, 1] are errors that name the
    received value."""
    with pytest.raises(ValueError, match="negative"):
        penalty_stiffness(np.array([1e-6, -1e-7]), 1e-4)
    with pytest.raises(ValueError, match="dt=0"):
        penalty_stiffness(np.array([1e-6]), 0.0)
    with pytest.raises(ValueError, match="fraction=1.5"):
        penalty_stiffness(np.array([1e-6]), 1e-4, 1.5)


# ----------------------------------------------------------------------------------------------
# rigid sphere, frictionless
# ----------------------------------------------------------------------------------------------


def test_rigid_sphere_penalty_force_and_energy():
    """A slave at depth d inside the sphere gets k d along the outward normal (x - c)/|x - c|;
    slaves outside get nothing; the stored energy is sum k d^2 / 2 and the ball receives minus
    the sum of the slave forces (rel. 1e-9 for the 110 mm radius)."""
    rng = np.random.default_rng(1)
    R, centre = 110.0, np.array([5.0, -3.0, 200.0])
    n_in, n_out = 6, 4
    dirs = _unit(rng, n_in + n_out)
    depth = np.r_[rng.uniform(0.01, 2.0, n_in), -rng.uniform(0.01, 5.0, n_out)]  # < 0: outside
    x = centre + (R - depth)[:, None] * dirs
    k = rng.uniform(5.0, 50.0, n_in + n_out)
    contact = RigidSphereContact(R, k, None, slaves=np.arange(10, 20))
    res = contact.step(x, np.zeros_like(x), centre, np.zeros(3), 1e-4)

    expected = np.zeros_like(x)
    expected[:n_in] = (k[:n_in] * depth[:n_in])[:, None] * dirs[:n_in]
    np.testing.assert_allclose(res.force, expected, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.penetration[:n_in], depth[:n_in], rtol=1e-9)
    assert np.all(res.penetration[n_in:] == 0) and res.n_active == n_in
    assert res.active.tolist() == [True] * n_in + [False] * n_out
    assert res.elastic_energy == pytest.approx(0.5 * np.sum(k[:n_in] * depth[:n_in] ** 2), rel=1e-9)
    np.testing.assert_allclose(res.normal_force_total, -expected.sum(axis=0), rtol=1e-12)
    np.testing.assert_allclose(res.master_force_total, -expected.sum(axis=0), rtol=1e-12)
    assert res.friction_dissipation == 0.0


def test_rigid_sphere_outside_and_far_nodes_skip_the_search(monkeypatch):
    """Slaves just outside the sphere carry no force (n_active 0, energy 0). Slaves whose bounding
    box misses the sphere are rejected before any distance is evaluated: with the distance kernel
    replaced by one that fails, the step still returns zero force, n_candidates 0, and it resets
    the friction state."""
    R, centre = 110.0, np.zeros(3)
    rng = np.random.default_rng(2)
    near = centre + (R + 0.5) * _unit(rng, 20)
    contact = RigidSphereContact(R, 10.0, CoulombFriction(), slaves=np.arange(20), margin=1.0)
    res = contact.step(near, np.zeros_like(near), centre, np.zeros(3), 1e-4)
    assert res.n_active == 0 and res.n_candidates == 20
    assert np.all(res.force == 0) and res.elastic_energy == 0

    def no_distances(*args):
        raise AssertionError("a distance was computed for slaves that cannot touch the sphere")

    monkeypatch.setattr(contact_module, "_dot", no_distances)
    far = rng.uniform(-50, 50, size=(20_000, 3)) + np.array([400.0, 0, 0])
    contact = RigidSphereContact(R, 10.0, CoulombFriction(), slaves=np.arange(far.shape[0]))
    res = contact.step(far, np.zeros_like(far), centre, np.zeros(3), 1e-4)
    assert res.n_candidates == 0 and res.n_active == 0 and not np.any(res.force)


# ----------------------------------------------------------------------------------------------
# Coulomb law
# ----------------------------------------------------------------------------------------------


def test_coulomb_hysteresis_loop_and_dissipation():
    """A contact point with constant normal force N = k_n d = 5 N (mu N = 1 N, k_t = 10 N/mm,
    stick limit s0 = mu N / k_t = 0.1 mm) is dragged 0 -> A -> -A -> A (A = 0.5 mm). The drag
    force F = -t is k_t u while sticking, exactly mu N when slipping; after each reversal it
    unloads elastically over 2 s0 and slips at -mu N (a parallelogram loop). The friction
    dissipation of the closed cycle equals the loop area 4 mu N (A - s0) = 1.6 mJ (by hand and by
    the trapezoidal integral of F du), to 1e-9."""
    law = CoulombFriction(mu=0.2, stiffness_ratio=1.0)
    k_n, depth = 10.0, 0.5
    N, k_t = k_n * depth, k_n
    muN, s0, A = 0.2 * N, 0.2 * N / k_n, 0.5
    h = 0.025
    up = np.arange(0, 21) * h  # 0 .. A
    path = np.r_[up, A - np.arange(1, 41) * h, -A + np.arange(1, 41) * h]  # 0 -> A -> -A -> A
    normal = np.array([[0.0, 0.0, 1.0]])
    t = np.zeros((1, 3))
    F, slipping, dissipation = [0.0], [False], [0.0]
    for du in np.diff(path):
        upd = law.return_map(t, np.array([[du, 0.0, 0.0]]), normal, np.array([N]), np.array([k_n]))
        t = upd.force
        assert t[0, 1] == 0 and t[0, 2] == 0
        F.append(-t[0, 0])
        slipping.append(bool(upd.slipping[0]))
        dissipation.append(float(upd.dissipation[0]))
    F, dissipation = np.array(F), np.array(dissipation)

    # closed form of the loop
    def expected(j):
        u = path[j]
        if j <= 20:  # virgin loading
            return min(k_t * u, muN)
        if j <= 60:  # A -> -A: unload from +muN at u = A
            return max(muN - k_t * (A - u), -muN)
        return min(-muN + k_t * (u + A), muN)  # -A -> A

    np.testing.assert_allclose(F, [expected(j) for j in range(path.size)], rtol=0, atol=1e-12)
    assert np.all(np.abs(F) <= muN * (1 + 1e-15))
    assert np.all(F[np.array(slipping)] == pytest.approx(np.sign(F[np.array(slipping)]) * muN, abs=1e-15))
    cycle = slice(21, None)  # increments of the closed loop A -> -A -> A
    loop_area = 4 * muN * (A - s0)
    assert dissipation[cycle].sum() == pytest.approx(loop_area, rel=1e-9)
    trapezoid = np.sum(0.5 * (F[20:-1] + F[21:]) * np.diff(path[20:]))
    assert trapezoid == pytest.approx(loop_area, rel=1e-9)
    assert dissipation[:21].sum() == pytest.approx(muN * (A - s0), rel=1e-9)  # virgin slip


def test_coulomb_state_transported_to_new_tangent_plane():
    """With no increment and a normal rotated by 30 degrees, the stored tangential force loses its
    normal component but keeps its magnitude (a rotation into the new tangent plane, to 1e-12)."""
    law = CoulombFriction(mu=0.2)
    theta = np.deg2rad(30.0)
    normal = np.array([[np.sin(theta), 0.0, np.cos(theta)]])
    upd = law.return_map(np.array([[0.7, 0.0, 0.0]]), np.zeros((1, 3)), normal, np.array([100.0]), np.array([10.0]))
    assert np.linalg.norm(upd.force) == pytest.approx(0.7, rel=1e-12)
    assert float(upd.force[0] @ normal[0]) == pytest.approx(0.0, abs=1e-12)
    assert upd.force[0, 0] > 0 and not upd.slipping[0] and upd.dissipation[0] == 0


def test_rigid_sphere_friction_state_resets_after_separation():
    """A node pressed into the sphere (N = k d) and moved tangentially by s < mu N / k_t carries the
    stick force k_t s (1e-12); moving with the translating ball (relative velocity zero) keeps it;
    after the node leaves contact and comes back, its friction force restarts from 0."""
    R, k, d = 110.0, 20.0, 0.5
    contact = RigidSphereContact(R, k, CoulombFriction(mu=0.2), slaves=np.array([7]))
    x_in = np.array([[0.0, 0.0, R - d]])
    dt, s = 1e-3, 0.002  # k_t s = 0.04 N < mu N = 2 N
    res = contact.step(x_in, np.array([[s / dt, 0, 0]]), np.zeros(3), np.zeros(3), dt)
    assert res.tangential_force[0] == pytest.approx([-k * s, 0, 0], abs=1e-12)
    assert not res.slipping[0]
    ball_v = np.array([25.0, -5.0, 0.0])  # node riding with the (non-spinning) ball: no new slip
    res = contact.step(x_in, ball_v[None], np.zeros(3), ball_v, dt)
    assert res.tangential_force[0] == pytest.approx([-k * s, 0, 0], abs=1e-12)
    res = contact.step(np.array([[0.0, 0.0, R + 1.0]]), np.zeros((1, 3)), np.zeros(3), np.zeros(3), dt)
    assert res.n_active == 0 and np.all(contact.tangential_state == 0)
    res = contact.step(x_in, np.zeros((1, 3)), np.zeros(3), np.zeros(3), dt)
    assert np.all(res.tangential_force == 0)


def test_block_sticks_when_pull_below_mu_W():
    """Node of mass m pressed by W onto the rigid sphere and pulled by T = 0.25 mu W: it sticks
    for all 300 steps. The undamped stick spring k_t driven by a step load, integrated by central
    difference with phase Omega (cos Omega = 1 - k_t dt^2 / 2m), peaks at
    (1 + 1/cos(Omega/2)) T/k_t (rel. 1e-3) and oscillates about the static stretch T/k_t
    (time mean within 2%)."""
    W, mu = 1.0, 0.2
    T = 0.25 * mu * W
    run = _block_on_sphere(T)
    k_t, m, dt = run["k"], run["m"], run["dt"]
    u = run["x"][:, 0]
    omega = np.arccos(1 - k_t * dt**2 / (2 * m))
    peak = (1 + 1 / np.cos(omega / 2)) * T / k_t
    assert not run["slipping"].any()
    assert u.max() == pytest.approx(peak, rel=1e-3)
    assert u.mean() == pytest.approx(T / k_t, rel=0.02)
    assert np.all(np.abs(run["x"][:, 1]) < 1e-12)


def test_block_slides_when_pull_above_mu_W():
    """Same node pulled by T = 1.5 mu W: it slips and accelerates at (T - mu W)/m; the mean
    acceleration over steps 10-300 matches within 2%, and the friction force equals mu |f_n|
    exactly in every slipping step."""
    W, mu = 1.0, 0.2
    T = 1.5 * mu * W
    run = _block_on_sphere(T)
    v, dt, m = run["v"][:, 0], run["dt"], run["m"]
    assert run["slipping"][2:].all()
    a_mean = (v[-1] - v[10]) / ((v.size - 1 - 10) * dt)
    assert a_mean == pytest.approx((T - mu * W) / m, rel=0.02)
    for (t, fn), slip in zip(run["friction"], run["slipping"]):
        if slip:
            assert np.linalg.norm(t) == pytest.approx(mu * fn, rel=1e-12)


# ----------------------------------------------------------------------------------------------
# deformable surface
# ----------------------------------------------------------------------------------------------


def test_surface_contact_flat_square_forces_and_reaction():
    """Slaves at depth d below a flat master square (outward normal +z) get k d along +z; each
    slave's reaction on the square's nodes is -w_i f with the barycentric weights of its contact
    point, so the master forces sum to minus the slave force and have zero moment about the
    contact point (to 1e-12); the total master force is -sum f."""
    points, tri = _square()
    slaves_xyz = np.array([[3.0, 2.0, -0.2], [7.0, 6.0, -0.1], [5.0, 5.0, -0.3]])
    x = np.r_[points, slaves_xyz]
    k = np.array([10.0, 20.0, 30.0])
    contact = SurfaceContact(np.arange(4, 7), tri, k, None)
    res = contact.step(x, np.zeros_like(x), 1e-4)
    depth = -slaves_xyz[:, 2]
    np.testing.assert_allclose(res.force, np.c_[np.zeros((3, 2)), k * depth], atol=1e-12)
    np.testing.assert_allclose(res.penetration, depth, rtol=1e-12)
    assert res.elastic_energy == pytest.approx(0.5 * np.sum(k * depth**2), rel=1e-12)
    np.testing.assert_allclose(res.master_force.sum(axis=0), -res.force.sum(axis=0), atol=1e-12)
    np.testing.assert_allclose(res.master_force_total, -res.force.sum(axis=0), atol=1e-12)
    assert np.all(res.master_force[4:] == 0)

    for i in range(3):  # one slave at a time: moment about its contact point
        single = SurfaceContact(np.array([4 + i]), tri, k[i], None)
        r = single.step(x, np.zeros_like(x), 1e-4)
        p = np.array([slaves_xyz[i, 0], slaves_xyz[i, 1], 0.0])
        moment = np.cross(points - p, r.master_force[:4]).sum(axis=0)
        np.testing.assert_allclose(moment, 0.0, atol=1e-12)
        np.testing.assert_allclose(r.master_force[:4].sum(axis=0), -r.force[0], atol=1e-12)


def test_surface_contact_ignores_far_deep_and_front_nodes():
    """Slaves outside the master's inflated bounding box are not candidates; a slave in front of
    the surface (g > 0) or deeper than search_fraction * local element size is not captured."""
    points, tri = _square()
    slaves_xyz = np.array(
        [
            [50.0, 50.0, -0.1],  # far away: rejected by the bounding box
            [5.0, 5.0, 0.2],  # in front of the surface
            [2.0, 8.0, -8.0],  # 8 mm deep, search depth 0.5 * 11.38 mm = 5.69 mm
            [8.0, 2.0, -0.4],  # genuine contact
        ]
    )
    x = np.r_[points, slaves_xyz]
    contact = SurfaceContact(np.arange(4, 8), tri, 10.0, CoulombFriction(), margin=20.0)
    res = contact.step(x, np.zeros_like(x), 1e-4)
    assert res.n_candidates == 3 and res.n_active == 1
    assert res.active.tolist() == [False, False, False, True]
    assert res.force[3] == pytest.approx([0, 0, 4.0])

    apart = x.copy()
    apart[4:] += np.array([0.0, 0.0, -100.0])
    res = SurfaceContact(np.arange(4, 8), tri, 10.0, None).step(apart, np.zeros_like(x), 1e-4)
    assert res.n_candidates == 0 and not np.any(res.force) and not np.any(res.master_force)


def test_surface_contact_friction_stick_then_slip():
    """A slave held at depth d = 0.5 mm below the square (N = k d = 5 N, mu N = 1 N, k_t = 10 N/mm)
    and dragged along x: the tangential force is -k_t u while k_t u < mu N, then exactly -mu N;
    the master receives the opposite force. Moving slave and master together (rigid translation)
    creates no friction."""
    points, tri = _square()
    k, d, dt, h = 10.0, 0.5, 1e-3, 0.02
    x = np.r_[points, [[3.0, 5.0, -d]]]
    contact = SurfaceContact(np.array([4]), tri, k, CoulombFriction(mu=0.2))
    v = np.zeros_like(x)
    contact.step(x, v, dt)
    for j in range(1, 11):
        v[:] = 0.0
        v[4, 0] = h / dt
        x[4, 0] += h
        res = contact.step(x, v, dt)
        u = j * h
        expected = min(k * u, 1.0)
        assert res.tangential_force[0, 0] == pytest.approx(-expected, abs=1e-12)
        assert res.slipping[0] == (k * u > 1.0 + 1e-12)
        assert res.master_force.sum(axis=0)[0] == pytest.approx(expected, abs=1e-12)

    rigid = SurfaceContact(np.array([4]), tri, k, CoulombFriction(mu=0.2))
    v = np.tile([30.0, -10.0, 0.0], (5, 1))
    for _ in range(5):
        res = rigid.step(x, v, dt)
        x = x + v * dt
        assert np.all(np.abs(res.tangential_force) < 1e-12)


def test_surface_contact_conserves_momentum():
    """Random slaves behind a wavy deformable master surface, random nodal velocities, friction
    on, 20 steps: slave plus master forces sum to zero (1e-12 N) at every step."""
    rng = np.random.default_rng(3)
    nx = 6
    gx, gy = np.meshgrid(np.linspace(0, 10, nx), np.linspace(0, 10, nx), indexing="ij")
    grid = np.c_[gx.ravel(), gy.ravel(), 0.3 * np.sin(gx.ravel()) * np.cos(gy.ravel())]
    idx = np.arange(nx * nx).reshape(nx, nx)
    a, b, c, e = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    tri = np.r_[np.c_[a, b, c], np.c_[a, c, e]]
    n_s = 40
    xy = rng.uniform(0.5, 9.5, size=(n_s, 2))
    z = 0.3 * np.sin(xy[:, 0]) * np.cos(xy[:, 1]) - rng.uniform(0.0, 0.5, n_s)
    x = np.r_[grid, np.c_[xy, z]]
    slaves = np.arange(nx * nx, nx * nx + n_s)
    contact = SurfaceContact(slaves, tri, rng.uniform(5, 50, n_s), CoulombFriction(mu=0.2))
    dt = 1e-3
    total_active = 0
    for _ in range(20):
        v = rng.normal(scale=20.0, size=x.shape)
        res = contact.step(x, v, dt)
        total_active += res.n_active
        net = res.force.sum(axis=0) + res.master_force.sum(axis=0)
        np.testing.assert_allclose(net, 0.0, atol=1e-12)
        x = x + v * dt
    assert total_active > 200 and res.friction_dissipation >= 0


def test_orient_outward_and_closed_master():
    """orient_outward re-winds randomly flipped faces of an octahedron so every normal points away
    from its centre; a slave 0.1 mm inside a face of that closed master is pushed out along the
    face's outward normal with force k * 0.1 (rel. 1e-9)."""
    points, tri = _octahedron()
    rng = np.random.default_rng(4)
    flipped = tri.copy()
    flip = rng.random(len(tri)) < 0.5
    flipped[flip] = flipped[flip][:, [0, 2, 1]]
    fixed = orient_outward(flipped, points, np.zeros(3))
    p0, p1, p2 = points[fixed[:, 0]], points[fixed[:, 1]], points[fixed[:, 2]]
    assert np.all(np.einsum("ij,ij->i", np.cross(p1 - p0, p2 - p0), (p0 + p1 + p2) / 3) > 0)
    np.testing.assert_array_equal(np.sort(fixed, axis=1), np.sort(tri, axis=1))

    n_face = np.ones(3) / np.sqrt(3)  # face (0, 2, 4), x + y + z = 10
    slave = (10 / 3) * np.ones(3) - 0.1 * n_face
    x = np.r_[points, slave[None]]
    res = SurfaceContact(np.array([6]), fixed, 25.0, None).step(x, np.zeros_like(x), 1e-4)
    assert res.n_active == 1
    np.testing.assert_allclose(res.force[0], 25.0 * 0.1 * n_face, rtol=1e-9)


def test_surface_contact_rejects_shared_nodes():
    """A slave that is also a master triangle node is an input error naming the node."""
    _, tri = _square()
    with pytest.raises(ValueError, match="also master triangle nodes"):
        SurfaceContact(np.array([2, 5]), tri, 1.0, None)
