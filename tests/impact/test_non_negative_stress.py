"""Von Mises stress is a norm, so no impact output may be negative: a surrogate whose network
decodes a negative stress predicts zero there and its own value elsewhere, and a trusted answer
refuses a result with a negative stress. Hand-weighted models on a synthetic scene of 40 nodes
and 6 frames (no database, well under a second)."""

from dataclasses import asdict
from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from toolkit.common.errors import AnswerError  # noqa: E402
from toolkit.common.training import MinMaxScaler, ModelBundle, torch_seeded  # noqa: E402
from toolkit.impact.database import SceneInputs  # noqa: E402
from toolkit.impact.networks import build_network  # noqa: E402
from toolkit.impact.surrogate import (  # noqa: E402
    CONFIGS,
    MODEL_KIND,
    OUTPUTS,
    Surrogate,
    item_features,
)
from toolkit.impact.trust import TrustedAnswer  # noqa: E402

TRAIN_VELOCITIES = (20.0, 50.0)  # mm/s


def _scene_inputs() -> SceneInputs:
    """40 nodes in a 60 x 40 x 80 mm box (the first 5 held), 6 frames over 0.3 s, a 10 mm ball
    starting 20 mm in front of the box and moving along -y."""
    rng = np.random.default_rng(0)
    points = rng.uniform([0.0, 0.0, 0.0], [60.0, 40.0, 80.0], size=(40, 3))
    fixed = np.zeros(40, dtype=bool)
    fixed[:5] = True
    return SceneInputs(points, fixed, np.linspace(0.05, 0.3, 6), np.array([30.0, 70.0, 40.0]),
                       np.array([0.0, -1.0, 0.0]), 10.0)


def _stress_bias(net) -> torch.Tensor:
    """The output bias of the von Mises channel (index 3) of a network of :func:`build_network`."""
    net = getattr(net, "net", net)  # behind a positional encoding
    if hasattr(net, "heads"):
        return net.heads[3].bias[0:1]
    head = net.head if hasattr(net, "head") else net.net[-1]
    return head.bias[3:4]


def _negative_half_model(name: str, inputs: SceneInputs) -> Surrogate:
    """The configuration ``name``'s network at random weights, its stress bias shifted so that
    the scaled stress it outputs at 41 mm/s is below 0 (below the training minimum, 0 MPa) at
    half the node-frames."""
    cfg = CONFIGS[name]
    x = item_features(inputs, TRAIN_VELOCITIES, cfg.features)
    x_scaler = MinMaxScaler.fit(x, cfg.inputs)
    y_scaler = MinMaxScaler([-1.0, -1.0, -1.0, 0.0], [1.0, 1.0, 1.0, 0.01], OUTPUTS)
    with torch_seeded(0):
        net = build_network(cfg.network, len(cfg.inputs), len(OUTPUTS), cfg.hidden, cfg.layers, cfg.fourier)
    xs = torch.from_numpy(x_scaler.transform(item_features(inputs, [41.0], cfg.features)).astype(np.float32))
    with torch.no_grad():
        _stress_bias(net).sub_(net(xs)[..., 3].median())
    bundle = ModelBundle(MODEL_KIND, asdict(cfg), {}, {"inputs": x_scaler, "outputs": y_scaler},
                         net.state_dict(), {"split": {"train_velocities": list(TRAIN_VELOCITIES)}})
    return Surrogate(bundle, net)


def _decoded_stress(model: Surrogate, inputs: SceneInputs, velocity: float) -> np.ndarray:
    """The network's stress unscaled (times the ball's travel for ``per_travel``), ``(F, N)`` MPa."""
    x = item_features(inputs, [velocity], model.config.features)
    xs = torch.from_numpy(model.bundle.scalers["inputs"].transform(x).astype(np.float32))
    with torch.no_grad():
        y = model.bundle.scalers["outputs"].inverse(model.network(xs).numpy().astype(np.float64))[..., 3]
    if model.config.per_travel:
        y = y * (x[..., 3] * x[..., 4])  # the travel in float32, as the model computes it
    return y.T


@pytest.mark.parametrize("name", ["paper", "strong", "baseline"])
def test_predicted_von_mises_is_zero_where_the_network_decodes_a_negative_stress(name):
    """Each configuration's network decodes a negative stress at about half the node-frames;
    the prediction is exactly 0 there, the decoded stress everywhere else, and nowhere negative."""
    inputs = _scene_inputs()
    model = _negative_half_model(name, inputs)
    decoded = _decoded_stress(model, inputs, 41.0)
    assert 0.3 < np.mean(decoded < 0.0) < 0.7
    _, vm = model.predict(41.0, inputs)
    assert vm.shape == (inputs.times.size, inputs.points.shape[0])
    assert vm.min() >= 0.0
    np.testing.assert_array_equal(vm[decoded < 0.0], 0.0)
    np.testing.assert_allclose(vm[decoded >= 0.0], decoded[decoded >= 0.0], rtol=1e-12, atol=0.0)


def test_an_answer_with_a_negative_stress_is_refused():
    """A trusted answer whose result has a negative (or NaN) von Mises stress raises, naming how
    many node-frames and the lowest value; a non-negative one is accepted."""
    u = np.zeros((2, 3, 3))

    def make(vm):
        return TrustedAnswer(SimpleNamespace(displacement=u, von_mises=np.asarray(vm)), "surrogate", "test",
                                   1.0, {}, {}, {})

    assert make([[0.0, 0.1, 0.2], [0.0, 0.0, 0.3]]).displacement is u
    with pytest.raises(AnswerError, match=r"2 of 6 node-frames .* \(lowest -0.002 MPa\)"):
        make([[0.0, -0.002, 0.2], [0.0, np.nan, 0.3]])
