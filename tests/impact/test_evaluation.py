"""The impact evaluation's figures show a simulation the evaluation tested, labelled with its
velocity and its role (held out or a training velocity)."""

import pytest

pytest.importorskip("torch")

import toolkit.impact.evaluation as evaluation  # noqa: E402
from toolkit.impact.surrogate import CONFIGS, train_surrogate  # noqa: E402


@pytest.mark.parametrize("split, role", [("random", "training velocity"), ("velocity", "held out")])
def test_fields_figure_shows_a_test_velocity(tiny_db, tmp_path, monkeypatch, split, role):
    """fields.png shows the fastest simulation with test items, as timeseries.png does: on the
    random split a training velocity (its test items are node series of the training
    simulations), on the velocity split the held-out 35 mm/s; every panel title names that
    velocity and its role."""
    model = train_surrogate(tiny_db, CONFIGS["baseline"].with_(epochs=2, patience=None), split, seed=0,
                            progress=False)
    ev = evaluation.evaluate_surrogate(model, tiny_db)
    shown = {}
    real = evaluation.plot_fields

    def recording(db, surrogate, path, sim=None, frames=None):
        fig = real(db, surrogate, path, sim=sim, frames=frames)
        shown["titles"] = [ax.get_title() for ax in fig.axes if ax.get_title()]
        shown["velocity"] = float(db.velocities[sim])
        return fig

    monkeypatch.setattr(evaluation, "plot_fields", recording)
    evaluation.write_evaluation(ev, tiny_db, model, tmp_path)
    assert shown["velocity"] in ev.metrics["test_velocities_mm_s"]
    assert shown["velocity"] == max(ev.metrics["test_velocities_mm_s"])
    assert shown["titles"] and all(f"{shown['velocity']:g} mm/s ({role})" in t for t in shown["titles"])
    assert (tmp_path / "fields.png").stat().st_size > 0


def test_a_prediction_writes_a_preview_unless_told_not_to(tiny_db, tmp_path):
    """Prediction.write draws preview.png of the last frame (with the rigid ball where it is then),
    as simulate does; preview=False skips it."""
    from toolkit.impact.surrogate import predict_scene

    model = train_surrogate(tiny_db, CONFIGS["baseline"].with_(epochs=1, patience=None), "random", seed=0,
                            progress=False)
    pred = predict_scene(model, 41.0)
    pred.write(tmp_path / "with")
    assert (tmp_path / "with" / "preview.png").stat().st_size > 0
    pred.write(tmp_path / "without", preview=False)
    assert not (tmp_path / "without" / "preview.png").exists()
    assert (tmp_path / "without" / "face.xdmf").exists()
