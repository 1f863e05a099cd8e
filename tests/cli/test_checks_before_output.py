"""Options a command cannot use are refused before it makes its output folder: held-out subjects
the database lacks, a CUDA device torch does not see, figure nodes or frames outside the
database. The same checks hold in Python (the library refuses) and on the command line."""

import numpy as np
import pytest

from toolkit.cli import main

needs_no_cuda = pytest.mark.skipif("__import__('torch').cuda.is_available()", reason="a CUDA GPU is visible")


def test_static_training_refuses_absent_test_subjects_before_making_the_model_folder(models, tmp_path):
    from toolkit.static.surrogate import SurrogateConfig, train_surrogate

    config = SurrogateConfig(network="tiny", coarse_radii=True, epochs=1, split="subjects", test_subjects=(7,))
    with pytest.raises(ValueError, match=r"test_subjects \[7\] are not in the database.*holds subjects \[0\]"):
        train_surrogate(models / "static.h5", config, out=tmp_path / "m", progress=False)
    assert not (tmp_path / "m").exists()


def test_static_training_refuses_holding_out_every_subject(models, tmp_path):
    from toolkit.static.surrogate import SurrogateConfig, train_surrogate

    config = SurrogateConfig(network="tiny", coarse_radii=True, epochs=1, split="subjects", test_subjects=(0,))
    with pytest.raises(ValueError, match="every subject"):
        train_surrogate(models / "static.h5", config, out=tmp_path / "m", progress=False)
    assert not (tmp_path / "m").exists()


@needs_no_cuda
@pytest.mark.parametrize("workflow", ["static", "impact"])
def test_training_on_an_unseen_cuda_device_is_refused_before_making_the_model_folder(workflow, models, tmp_path,
                                                                                    capsys):
    data = models / f"{workflow}.h5"
    code = main([workflow, "train", "--data", str(data), "--epochs", "1", "--device", "cuda",
                 "--out", str(tmp_path / "m")])
    err = capsys.readouterr().err
    assert code == 2
    assert "sees no CUDA GPU" in err and "--device" in err
    assert not (tmp_path / "m").exists()


def test_static_train_names_the_test_subjects_option(models, tmp_path, capsys):
    code = main(["static", "train", "--data", str(models / "static.h5"), "--test-subjects", "7", "--epochs", "1",
                 "--network", "tiny", "--out", str(tmp_path / "m")])
    assert code == 2
    assert "(command line: --test-subjects)" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


@pytest.mark.parametrize("option, value, expected", [
    ("--nodes", "999999", r"nodes \[999999\] out of range"),
    ("--frames", "99", r"frames \[99\] out of range"),
    ("--nodes", ",", "nodes is an empty list"),
])
def test_impact_evaluate_checks_its_figure_options_before_writing(option, value, expected, models, tmp_path,
                                                                  capsys):
    import re

    code = main(["impact", "evaluate", "--model", str(models / "imodel"), "--data", str(models / "impact.h5"),
                 option, value, "--out", str(tmp_path / "e")])
    assert code == 2
    assert re.search(expected, capsys.readouterr().err)
    assert not (tmp_path / "e").exists()


def test_impact_evaluation_writes_nothing_for_a_node_that_is_not_a_test_item(models, tmp_path):
    from toolkit.impact.database import load_database
    from toolkit.impact.evaluation import evaluate_surrogate, write_evaluation
    from toolkit.impact.surrogate import Surrogate

    model, db = Surrogate.load(models / "imodel"), load_database(models / "impact.h5")
    ev = evaluate_surrogate(model, db)
    sims = np.unique(ev.items // db.n_nodes)
    sim = int(sims[np.argmax(db.velocities[sims])])  # the figures show the fastest simulation with test items
    shown = set((ev.items[ev.items // db.n_nodes == sim] % db.n_nodes).tolist())
    outside = next(n for n in range(db.n_nodes) if n not in shown)
    with pytest.raises(ValueError, match="not test items"):
        write_evaluation(ev, db, model, tmp_path / "e", nodes=[outside])
    assert not (tmp_path / "e").exists()
