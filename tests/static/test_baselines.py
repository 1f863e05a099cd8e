"""The baselines the static surrogate is compared with: linear superposition through an
influence matrix, POD with a regression on the plan parameters, and the two together (the
linear solution plus a POD regression of its residual)."""

import numpy as np
import pytest

from toolkit.common.phantoms.phantom import face_hex
from toolkit.static import default_plan, simulate
from toolkit.static.baselines import InfluenceMatrix, LinearPlusPOD, PODRegression, quadratic_features
from toolkit.static.boundary import NodeType


def test_influence_matrix_is_exact_for_linear_without_sliding():
    """Without sliding or lip contact, one linear increment is K u = 0 with the bone-driven and
    fixed nodes prescribed: the condensed influence matrix, fed the FE's displacement of the
    driven nodes, reproduces the FE displacement at every node to 1e-9 of its maximum; a
    scaled input scales the output (superposition)."""
    ph = face_hex("coarse")
    res = simulate(ph, default_plan(ph), 1, "linear", "none")
    bc = res.boundary
    driven, fixed = bc.nodes(NodeType.MOVING), bc.nodes(NodeType.FIXED)
    im = InfluenceMatrix.build(ph.mesh, driven, fixed)
    u = im.predict(res.displacement)
    np.testing.assert_allclose(u, res.displacement, rtol=0, atol=1e-9 * np.abs(res.displacement).max())
    np.testing.assert_allclose(im.predict(0.5 * res.displacement[driven]), 0.5 * u, atol=1e-12)
    assert im.H.shape == (3 * im.free.size, 3 * driven.size)
    with pytest.raises(ValueError, match="expected"):
        im.predict(np.zeros((5, 3)))


def test_influence_matrix_on_amg_agrees_with_the_factor():
    """Where a factor would be too large the influence matrix solves K_ff by AMG-CG (the FE's
    rtol 1e-9): on the coarse phantom, forced to ``amg``, its prediction and its solves (one
    right-hand side or several) agree with the factorized one to 1e-7 of their largest value;
    ``auto`` factorizes this small face, and an unknown solver is refused."""
    ph = face_hex("coarse")
    res = simulate(ph, default_plan(ph), 1, "linear", "none")
    bc = res.boundary
    driven, fixed = bc.nodes(NodeType.MOVING), bc.nodes(NodeType.FIXED)
    direct = InfluenceMatrix.build(ph.mesh, driven, fixed, solver="superlu")
    amg = InfluenceMatrix.build(ph.mesh, driven, fixed, solver="amg")
    assert (direct.method, amg.method) == ("superlu", "amg")
    assert InfluenceMatrix.build(ph.mesh, driven, fixed).method == "superlu"
    u = direct.predict(res.displacement)
    np.testing.assert_allclose(amg.predict(res.displacement), u, rtol=0, atol=1e-7 * np.abs(u).max())
    columns = direct.coupling[:, :4].toarray()  # several right-hand sides at once, as H solves them
    x = direct.solve(columns)
    np.testing.assert_allclose(amg.solve(columns), x, rtol=0, atol=1e-7 * np.abs(x).max())
    with pytest.raises(ValueError, match="solver = 'cg'; expected 'auto', 'superlu' or 'amg'"):
        InfluenceMatrix.build(ph.mesh, driven, fixed, solver="cg")


def test_pod_regression_recovers_a_quadratic_family():
    """Displacements that are three fixed fields weighted by quadratic functions of 4
    parameters lie in a 3-dimensional space: POD keeps 3 modes (all the energy) and the
    quadratic ridge regression predicts unseen parameters to 1e-6 of the field size."""
    rng = np.random.default_rng(0)
    fields = rng.normal(size=(3, 50, 3))
    def family(p):
        w = np.stack([1 + p[:, 0] * p[:, 1], p[:, 2] ** 2 - p[:, 3], 0.5 * p[:, 0]], axis=1)
        return np.einsum("sk,knc->snc", w, fields)
    train, test = rng.uniform(-1, 1, (80, 4)), rng.uniform(-1, 1, (10, 4))
    model = PODRegression.fit(train, family(train), ridge=1e-12)
    assert model.modes.shape[0] == 3 and model.energy > 1 - 1e-9
    np.testing.assert_allclose(model.predict(test), family(test), atol=1e-6 * np.abs(fields).max())
    assert quadratic_features(np.ones((2, 3))).shape == (2, 1 + 3 + 6)
    with pytest.raises(ValueError, match="5 columns"):
        model.predict(np.zeros((1, 5)))


def test_linear_plus_pod_adds_the_regressed_residual_to_any_linear_solution():
    """When the FE displacement is a per-sample linear solution (arbitrary, not a function of the
    parameters) plus a residual from a quadratic family of 4 parameters, POD alone cannot
    represent it, but LinearPlusPOD predicts unseen samples to 1e-6 of the field size: it
    regresses only the residual and adds each sample's own linear solution."""
    rng = np.random.default_rng(1)
    fields = rng.normal(size=(2, 40, 3))

    def residual(p):
        w = np.stack([p[:, 0] * p[:, 1], p[:, 2] - p[:, 3] ** 2], axis=1)
        return np.einsum("sk,knc->snc", w, fields)

    train, test = rng.uniform(-1, 1, (60, 4)), rng.uniform(-1, 1, (10, 4))
    lin_train, lin_test = rng.normal(size=(60, 40, 3)), rng.normal(size=(10, 40, 3))
    model = LinearPlusPOD.fit(train, lin_train + residual(train), lin_train, ridge=1e-12)
    np.testing.assert_allclose(model.predict(test, lin_test), lin_test + residual(test), atol=1e-6)
    pod_only = PODRegression.fit(train, lin_train + residual(train))
    assert np.abs(pod_only.predict(test) - (lin_test + residual(test))).mean() > 0.5
    with pytest.raises(ValueError, match="same shape"):
        LinearPlusPOD.fit(train, lin_train, lin_train[:, :5])
