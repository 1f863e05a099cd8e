"""Shared training utilities: scaling round trips, seeds, devices, group-wise splits, the training
loop (a small regression it must learn; early stopping; checkpoint and exact resume; Ctrl-C),
and model directories that refuse what they were not built for."""

import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from toolkit.common.config_diff import IncompatibleError, differences  # noqa: E402
from toolkit.common.training import (  # noqa: E402
    MinMaxScaler,
    ModelBundle,
    TrainConfig,
    generators,
    group_counts,
    resolve_device,
    split_groups,
    torch_seeded,
    train,
)


def test_min_max_scaler_maps_to_unit_interval_and_round_trips_json():
    """Each feature's min goes to 0 and max to 1; inverse(transform(x)) = x to round-off; a constant
    feature maps to 0 and back; the JSON round trip is exact (the same bits); torch tensors keep
    their dtype."""
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.uniform(-3, 7, 100), rng.normal(size=100) * 1e-3, np.full(100, 2.5)])
    s = MinMaxScaler.fit(x, names=["a_mm", "b_mpa", "c"])
    y = s.transform(x)
    np.testing.assert_allclose(y[:, :2].min(axis=0), 0.0, atol=1e-15)
    np.testing.assert_allclose(y[:, :2].max(axis=0), 1.0, atol=1e-15)
    assert np.all(y[:, 2] == 0.0)
    np.testing.assert_allclose(s.inverse(y), x, rtol=1e-14, atol=1e-15)
    back = MinMaxScaler.from_dict(json.loads(json.dumps(s.to_dict())))
    assert back == s and np.array_equal(back.transform(x), y)
    t = s.transform(torch.tensor(x, dtype=torch.float32))
    assert t.dtype == torch.float32 and torch.allclose(t, torch.tensor(y, dtype=torch.float32), atol=1e-6)
    with pytest.raises(ValueError, match=r"fitted on 3 features .*got an array with 2"):
        s.transform(x[:, :2])


def test_seeds_reproduce_and_leave_global_state_alone():
    """The same seed gives the same numpy draws, torch draws and initial weights; building a model
    under torch_seeded does not change torch's global generator."""
    a_np, a_t = generators(5)
    b_np, b_t = generators(5)
    assert np.array_equal(a_np.random(4), b_np.random(4))
    assert torch.equal(torch.rand(4, generator=a_t), torch.rand(4, generator=b_t))
    before = torch.random.get_rng_state()
    with torch_seeded(3):
        w1 = torch.nn.Linear(4, 2).weight.detach().clone()
    with torch_seeded(3):
        w2 = torch.nn.Linear(4, 2).weight.detach().clone()
    assert torch.equal(w1, w2)
    assert torch.equal(before, torch.random.get_rng_state())
    with pytest.raises(ValueError, match="seed must be a non-negative integer, got -1"):
        generators(-1)


def test_device_resolution():
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="'tpu'"):
        resolve_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match="sees no CUDA GPU"):
            resolve_device("cuda")


def test_group_split_keeps_groups_whole_and_is_seeded():
    """Items of one group land in one split; the splits partition the items; the group counts
    follow the fractions (largest remainder: 6 groups at 0.7/0.15/0.15 -> 4/1/1); the same seed
    gives the same split and another seed another one."""
    groups = np.repeat([20, 26, 32, 38, 44, 50], 7)
    tr, va, te = split_groups(groups, (0.7, 0.15, 0.15), seed=1)
    assert np.array_equal(np.sort(np.concatenate([tr, va, te])), np.arange(groups.size))
    sets = [set(groups[i]) for i in (tr, va, te)]
    assert [len(s) for s in sets] == [4, 1, 1] and not (sets[0] & sets[1] or sets[0] & sets[2] or sets[1] & sets[2])
    again = split_groups(groups, (0.7, 0.15, 0.15), seed=1)
    assert all(np.array_equal(a, b) for a, b in zip((tr, va, te), again))
    assert any(not np.array_equal(a, b) for a, b in zip((tr, va, te), split_groups(groups, (0.7, 0.15, 0.15), 2)))
    items = split_groups(np.arange(1000), (0.76, 0.24), seed=0)  # one item per group: a random item split
    assert [i.size for i in items] == [760, 240]
    assert list(group_counts(3, (0.9, 0.05, 0.05))) == [1, 1, 1]
    with pytest.raises(ValueError, match="sum to 1"):
        split_groups(groups, (0.5, 0.2), seed=0)


def _regression(n=2000, seed=0):
    """y = sin(3 x0) + x1^2 on [0, 1]^2: a smooth target whose standard deviation is ~0.4."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(0, 1, size=(n, 2)).astype(np.float32)
    y = (np.sin(3 * x[:, :1]) + x[:, 1:] ** 2).astype(np.float32)
    return x, y


def _mlp(seed=0):
    with torch_seeded(seed):
        return torch.nn.Sequential(torch.nn.Linear(2, 32), torch.nn.Tanh(), torch.nn.Linear(32, 1))


def test_training_loop_learns_a_smooth_function():
    """A 32-unit MLP trained with Adam and MSE for 150 epochs (batch 100) on 1,600 points of
    y = sin(3 x0) + x1^2 reaches a validation RMSE under 0.05, a tenth of the target's standard
    deviation (the RMSE of the best constant predictor); the model ends holding the best epoch's
    weights (its validation loss equals the reported best)."""
    x, y = _regression()
    model = _mlp()
    cfg = TrainConfig(epochs=150, batch_size=100, lr=1e-2, patience=None, progress=False)
    result = train(model, torch.nn.functional.mse_loss, (x[:1600], y[:1600]), (x[1600:], y[1600:]), cfg)
    with torch.no_grad():
        pred = model(torch.tensor(x[1600:])).numpy()
    val_rmse = float(np.sqrt(np.mean((pred - y[1600:]) ** 2)))
    assert y.std() > 0.35 and val_rmse < 0.1 * y.std()
    assert val_rmse**2 == pytest.approx(result.best_val_loss, rel=1e-4)
    assert list(result.history.columns) == ["epoch", "train_loss", "val_loss", "seconds", "lr"]
    assert (result.history.lr == 1e-2).all()  # the default schedule is constant


def test_early_stopping_stops_when_validation_stalls():
    """With a validation set the model cannot fit (pure noise), the validation loss stops improving
    and training stops after `patience` epochs without improvement: best_epoch + patience epochs."""
    x, y = _regression(400)
    noise = np.random.default_rng(9).normal(size=(100, 1)).astype(np.float32)
    cfg = TrainConfig(epochs=500, batch_size=50, lr=1e-2, patience=5, progress=False)
    result = train(_mlp(), torch.nn.functional.mse_loss, (x[:300], y[:300]), (x[300:], noise), cfg)
    assert result.stopped == "early_stopping"
    assert len(result.history) == result.best_epoch + 5 < 500
    assert result.stop_reason == "early stopping: no validation improvement in 5 epochs"


def test_the_stop_reason_is_said_in_words():
    """Why training stopped reads as a sentence with its limit, never the code word twice
    ("2 epochs (epochs)"); an unknown code is refused naming the known ones."""
    from toolkit.common.training import stop_reason

    x, y = _regression(200)
    cfg = TrainConfig(epochs=2, batch_size=50, progress=False)
    result = train(_mlp(), torch.nn.functional.mse_loss, (x[:150], y[:150]), (x[150:], y[150:]), cfg)
    assert result.stopped == "epochs" and result.stop_reason == "epoch limit of 2 reached"
    assert stop_reason("time_limit", TrainConfig(max_seconds=45.0)) == "time limit of 45 s reached"
    assert stop_reason("epochs") == "epoch limit reached"
    with pytest.raises(ValueError, match="stopped = 'done'; expected one of"):
        stop_reason("done")


def test_resume_continues_exactly_and_refuses_another_configuration(tmp_path):
    """Training 6 epochs in one go equals training 3, stopping, and resuming to 6 from the
    checkpoint (same weights bit for bit: optimizer, generator and epoch are restored). A checkpoint
    is refused for another learning rate, naming it."""
    x, y = _regression(500)
    data = ((x[:400], y[:400]), (x[400:], y[400:]))
    ck = tmp_path / "ck.pt"
    cfg = TrainConfig(epochs=6, batch_size=64, lr=5e-3, patience=None, progress=False)
    straight = _mlp()
    train(straight, torch.nn.functional.l1_loss, *data, cfg)
    first = _mlp()
    train(first, torch.nn.functional.l1_loss, *data, TrainConfig(**{**cfg.__dict__, "epochs": 3}), checkpoint=ck)
    resumed = _mlp(seed=99)  # weights come from the checkpoint, not from here
    result = train(resumed, torch.nn.functional.l1_loss, *data, cfg, checkpoint=ck, resume=True)
    assert result.resumed_from == 3 and len(result.history) == 6
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)
    with pytest.raises(IncompatibleError, match=r"train\.lr: stored 0\.005, asked 0\.001"):
        train(_mlp(), torch.nn.functional.l1_loss, *data, TrainConfig(**{**cfg.__dict__, "lr": 1e-3}),
              checkpoint=ck, resume=True)


def test_interrupt_leaves_the_last_checkpoint_valid(tmp_path):
    """A Ctrl-C (KeyboardInterrupt raised by the loss in epoch 3) propagates; the checkpoint on disk
    is epoch 2's and resumes to the end."""
    x, y = _regression(300)
    data = ((x[:200], y[:200]), (x[200:], y[200:]))
    ck = tmp_path / "ck.pt"
    calls = {"n": 0}

    def flaky(pred, target):
        calls["n"] += pred.requires_grad  # training batches only
        if calls["n"] == 2 * 4 + 1:  # 4 training batches per epoch: first batch of epoch 3
            raise KeyboardInterrupt
        return torch.nn.functional.l1_loss(pred, target)

    cfg = TrainConfig(epochs=4, batch_size=50, lr=1e-3, patience=None, progress=False)
    with pytest.raises(KeyboardInterrupt):
        train(_mlp(), flaky, *data, cfg, checkpoint=ck)
    assert torch.load(ck, weights_only=False)["epoch"] == 2
    result = train(_mlp(), torch.nn.functional.l1_loss, *data, cfg, checkpoint=ck, resume=True)
    assert result.resumed_from == 2 and len(result.history) == 4


def test_cosine_schedule_follows_its_closed_form_and_resumes_on_its_curve(tmp_path):
    """With ``lr_schedule="cosine"`` the rate of epoch k (1-based) of E is
    lr (f + (1 - f)(1 + cos(pi (k - 1) / E)) / 2) exactly; with a time limit the spent fraction
    is the larger of the epoch and time fractions; a run interrupted after epoch 3 and resumed
    ends with the same weights, bit for bit, as one run (the rate depends only on the epoch
    count and the recorded training time, which for an epoch budget is the epoch count)."""
    from toolkit.common.training.loop import learning_rate

    x, y = _regression(300)
    data = ((x[:200], y[:200]), (x[200:], y[200:]))
    cfg = TrainConfig(epochs=6, batch_size=50, lr=4e-3, patience=None, progress=False, lr_schedule="cosine",
                      final_lr_fraction=0.05)
    straight = _mlp()
    result = train(straight, torch.nn.functional.l1_loss, *data, cfg)
    k = np.arange(6)
    expected = 4e-3 * (0.05 + 0.95 * 0.5 * (1 + np.cos(np.pi * k / 6)))
    np.testing.assert_allclose(result.history.lr, expected, rtol=1e-12)
    timed = TrainConfig(epochs=1000, lr=1.0, max_seconds=10.0, lr_schedule="cosine", final_lr_fraction=0.01)
    assert learning_rate(timed, 2, 5.0) == pytest.approx(0.01 + 0.99 * 0.5)  # half the time spent
    assert learning_rate(timed, 2, 50.0) == pytest.approx(0.01)  # past the limit: the final rate
    with pytest.raises(ValueError, match="lr_schedule 'step'"):
        TrainConfig(lr_schedule="step")

    ck, calls = tmp_path / "ck.pt", {"n": 0}

    def flaky(pred, target):
        calls["n"] += pred.requires_grad
        if calls["n"] == 3 * 4 + 1:  # first training batch of epoch 4
            raise KeyboardInterrupt
        return torch.nn.functional.l1_loss(pred, target)

    with pytest.raises(KeyboardInterrupt):
        train(_mlp(), flaky, *data, cfg, checkpoint=ck)
    resumed = _mlp(seed=7)
    train(resumed, torch.nn.functional.l1_loss, *data, cfg, checkpoint=ck, resume=True)
    for a, b in zip(straight.state_dict().values(), resumed.state_dict().values()):
        assert torch.equal(a, b)


def test_model_bundle_round_trip_and_refusals(tmp_path):
    """A saved bundle loads back with equal weights, scalers and config; another kind, another
    data signature (naming the key and both values) and a missing file are refused clearly."""
    model = _mlp()
    scaler = MinMaxScaler([0.0, 1.0], [2.0, 3.0], ["x_mm", "v_mm_s"])
    bundle = ModelBundle("toolkit.test.mlp", {"hidden": 32}, {"n_nodes": 10, "features": ["x_mm", "v_mm_s"]},
                         {"inputs": scaler}, model.state_dict(), {"train_seconds": 1.5})
    bundle.save(tmp_path / "m")
    back = ModelBundle.load(tmp_path / "m", kind="toolkit.test.mlp")
    assert back.scalers["inputs"] == scaler and back.config == {"hidden": 32} and back.extra["train_seconds"] == 1.5
    for k, v in model.state_dict().items():
        assert torch.equal(back.state_dict[k], v)
    with pytest.raises(IncompatibleError,
                       match="holds a 'toolkit.test.mlp' model, expected 'toolkit.impact.surrogate'"):
        ModelBundle.load(tmp_path / "m", kind="toolkit.impact.surrogate")
    with pytest.raises(IncompatibleError, match="n_nodes: stored 10, asked 12"):
        back.check_data({"n_nodes": 12, "features": ["x_mm", "v_mm_s"]})
    (tmp_path / "m" / "model.pt").unlink()
    with pytest.raises(FileNotFoundError, match="model.pt is missing"):
        ModelBundle.load(tmp_path / "m")


def test_differences_name_nested_keys():
    assert differences({"a": {"b": 1, "c": [1, 2]}, "d": 1.0}, {"a": {"b": 2, "c": [1, 2]}, "e": 3}) == [
        ("a.b", 1, 2), ("d", 1.0, "<missing>"), ("e", "<missing>", 3)]


def test_extrapolation_lists_each_parameter_outside_its_training_range():
    """Only the parameters outside their range are listed, with the distance in their unit; a
    value on the range's edge is inside; a model without ranges says "unknown"; the line the CLI
    prints names each parameter, its value and its training range."""
    from toolkit.common.training import describe_extrapolation, extrapolation

    ranges = {"a_mm": [2.0, 11.0], "b_deg": [-5.0, 5.0]}
    ex = extrapolation({"a_mm": 20.0, "b_deg": 5.0}, ranges)
    assert ex == {"outside": True, "parameters": {"a_mm": {"value": 20.0, "train_range": [2.0, 11.0],
                                                           "outside_by": 9.0}}}
    assert describe_extrapolation(ex) == ("OUTSIDE the training data, the model extrapolates: a_mm = 20 "
                                          "(trained 2 to 11, 9 outside)")
    inside = extrapolation({"a_mm": 2.0, "b_deg": -1.0}, ranges)
    assert inside == {"outside": False, "parameters": {}}
    assert describe_extrapolation(inside) == "inside the training data"
    unknown = extrapolation({"a_mm": 20.0}, None, "plans")
    assert unknown["outside"] == "unknown" and "training plans" in describe_extrapolation(unknown)
    with pytest.raises(KeyError, match="no training range for 'c'"):
        extrapolation({"c": 1.0}, ranges)
    # a range of one value: anything but that value is outside
    assert extrapolation({"c": 1e-6}, {"c": [0.0, 0.0]})["parameters"]["c"]["outside_by"] == pytest.approx(1e-6)
