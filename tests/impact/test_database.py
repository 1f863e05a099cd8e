"""The impact learning database: what a record holds (and that it agrees with the simulation it
came from), resuming, refusing another scene, recorded failures, local processes, a Dask
LocalCluster, and the `toolkit impact database` command."""

import json

import h5py
import numpy as np
import pandas as pd
import pytest

from toolkit.cli import main
from toolkit.common.config_diff import IncompatibleError
from toolkit.common.training.database import read_failures, read_index
from toolkit.impact import simulate
from toolkit.impact.database import build_database, default_held_out, load_database, velocity_key
from toolkit.impact.simulate import face_mesh, fixed_nodes

from .conftest import TINY_HELD_OUT, TINY_VELOCITIES, tiny_scene

#: the quickest impact runs: explicit dynamics with mass scaling 100
EXPLICIT = ["--integrator", "explicit", "--mass-scaling", "100"]


def test_default_held_out_velocities_sit_between_the_paper_ones():
    assert default_held_out([20, 26, 32, 38, 44, 50]) == [23.0, 35.0, 47.0]


def test_records_hold_the_simulation_fields_and_their_inputs(tiny_db, tiny_db_path):
    """Seven simulations sorted by velocity, the held-out one flagged; fields (S, F, N, 3) mm and
    (S, F, N) MPa on the shared face; the shared fixed mask is the scene's fixed nodes (bone side
    and band); the stored scene is the base scene; and the 50 mm/s record equals a fresh
    simulation of that case (float32 storage: 1e-5 relative). The index table (plain h5py +
    pandas) has one row per simulation with its maxima."""
    scene = tiny_scene()
    assert tiny_db.velocities.tolist() == sorted(TINY_VELOCITIES + TINY_HELD_OUT)
    assert tiny_db.held_out.tolist() == [v in TINY_HELD_OUT for v in tiny_db.velocities]
    face = face_mesh(scene)
    s, f, n = 7, 12, face.n_points
    assert tiny_db.displacement.shape == (s, f, n, 3) and tiny_db.von_mises.shape == (s, f, n)
    steps = int(tiny_db.index["steps"].iloc[0])  # frames fall on the nearest time step
    np.testing.assert_allclose(tiny_db.times, np.linspace(0, 0.36, 13)[1:], atol=0.5 * 0.36 / steps + 1e-12)
    np.testing.assert_array_equal(np.flatnonzero(tiny_db.fixed), fixed_nodes(scene, face))
    np.testing.assert_array_equal(tiny_db.points, face.points)
    assert tiny_db.scene.with_ball(velocity=50.0) == scene.with_ball(velocity=50.0)
    fresh = simulate(scene.with_ball(velocity=50.0), preview=False)
    k = int(np.flatnonzero(tiny_db.velocities == 50.0)[0])
    np.testing.assert_allclose(tiny_db.displacement[k], fresh.displacement, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(tiny_db.von_mises[k], fresh.von_mises, rtol=1e-5, atol=1e-9)
    with h5py.File(tiny_db_path) as h5:
        plain = pd.DataFrame(h5["index"][()])
    assert len(plain) == 7
    row = read_index(tiny_db_path).set_index("key").loc[velocity_key(50.0)]
    assert row["max_von_mises_mpa"] == pytest.approx(float(tiny_db.von_mises[k].max()), rel=1e-6)
    assert row["max_equivalent_plastic_strain"] > 0 and row["plastic_volume_fraction"] > 0
    assert read_index(tiny_db_path).set_index("key").loc["v20", "max_equivalent_plastic_strain"] == 0


def test_resume_adds_only_missing_velocities_and_refuses_another_scene(tmp_path):
    """A second run with one more velocity simulates only that one; a run with another fidelity
    (mass scaling 50) on the same file is refused, naming the setting and both values."""
    scene = tiny_scene()
    path = tmp_path / "db.h5"
    build_database(path, [30.0], [], scene, workers=0, progress=False)
    report = build_database(path, [30.0, 40.0], [], scene, workers=0, progress=False)
    assert report.done == ["v40"] and report.skipped == ["v30"]
    with pytest.raises(IncompatibleError, match=r"scene\.fidelity\.mass_scaling: stored 100\.0, asked 50\.0"):
        build_database(path, [30.0], [], scene.with_fidelity(integrator="explicit", mass_scaling=50.0), workers=0,
                       progress=False)


def test_a_failing_simulation_is_recorded_and_the_others_kept(tmp_path, monkeypatch):
    """A simulation that stops (here the 50 mm/s one raises an instability) is recorded as a
    failure with its reason, while 20 mm/s finishes; a rerun skips both."""
    from toolkit.impact import database
    from toolkit.impact.explicit import InstabilityError

    real = database.SimulationWorker.__call__

    def unstable_at_50(self, params):
        if params["velocity"] == 50.0:
            raise InstabilityError("inverted element 12 (test)", 0.51, "face", 12, "a shorter duration")
        return real(self, params)

    monkeypatch.setattr(database.SimulationWorker, "__call__", unstable_at_50)
    scene = tiny_scene()
    path = tmp_path / "db.h5"
    report = build_database(path, [20.0, 50.0], [], scene, workers=0, progress=False)
    assert report.done == ["v20"] and list(report.failed) == ["v50"]
    assert "InstabilityError" in report.failed["v50"] and "inverted" in report.failed["v50"]
    assert list(read_failures(path)["key"]) == ["v50"]
    again = build_database(path, [20.0, 50.0], [], scene, workers=0, progress=False)
    assert sorted(again.skipped) == ["v20", "v50"] and not again.done


@pytest.mark.long
def test_local_processes_and_a_dask_local_cluster_fill_the_same_database(tmp_path):
    """One velocity in a spawned worker process (the default executor) and another on a Dask
    LocalCluster (one worker process) land in one database with identical fields to an
    in-process run."""
    distributed = pytest.importorskip("distributed")
    scene = tiny_scene()
    path = tmp_path / "db.h5"
    build_database(path, [30.0], [], scene, workers=1, progress=False)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        report = build_database(path, [30.0, 45.0], [], scene, executor=client, progress=False)
    assert report.done == ["v45"]
    build_database(tmp_path / "ref.h5", [30.0, 45.0], [], scene, workers=0, progress=False)
    a, b = load_database(path), load_database(tmp_path / "ref.h5")
    np.testing.assert_array_equal(a.displacement, b.displacement)


def test_database_command(tmp_path, capsys):
    """`toolkit impact database` with velocities, held-out velocities and fidelity options builds the
    database, prints the per-velocity yield table, and refuses a file that is not an impact database."""
    out = tmp_path / "db.h5"
    argv = ["impact", "database", "--velocities", "30,50", "--held-out", "40", "--resolution", "coarse",
            "--ball", "rigid", "--order", "1", *EXPLICIT, "--duration", "0.36", "--workers", "0",
            "--out", str(out)]
    assert main(argv) == 0
    printed = capsys.readouterr().out
    assert "3 simulated" in printed and "max_von_mises_mpa" in printed
    db = load_database(out)
    assert db.velocities.tolist() == [30.0, 40.0, 50.0] and db.held_out.tolist() == [False, True, False]
    cfg = json.loads(h5py.File(out, "r").attrs["config"])
    assert cfg["scene"]["face"]["support"] == "skull" and "velocity" not in cfg["scene"]["ball"]
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as h5:
        h5.attrs["format"] = "something else"
    assert main(argv[:-1] + [str(other)]) == 2
    assert "is not a 'toolkit.impact.database' database" in capsys.readouterr().err


def test_an_interrupted_database_is_usable_at_once_and_the_rerun_finishes_it(tmp_path, monkeypatch):
    """Ctrl-C during the 40 mm/s simulation (after 30 mm/s finished): a copy of the .h5 alone
    loads the 30 mm/s simulation with a warning "interrupted database ...: 1 of 2 simulations
    done; rerun `toolkit impact database` with the same options to finish it"; a Ctrl-C during
    the very first simulation leaves a file whose loading is refused with "0 of 1"; the rerun of
    the same build finishes the first and then loads without a warning."""
    import shutil
    import warnings

    from toolkit.common.training.database import DatabaseError, IncompleteDatabaseWarning
    from toolkit.impact import database

    real = database.SimulationWorker.__call__

    def interrupted_at_40(self, params):
        if params["velocity"] == 40.0:
            raise KeyboardInterrupt
        return real(self, params)

    scene = tiny_scene()
    path = tmp_path / "db.h5"
    monkeypatch.setattr(database.SimulationWorker, "__call__", interrupted_at_40)
    with pytest.raises(KeyboardInterrupt):
        build_database(path, [30.0, 40.0], [], scene, workers=0, progress=False)
    with pytest.raises(KeyboardInterrupt):
        build_database(tmp_path / "empty.h5", [40.0], [], scene, workers=0, progress=False)
    monkeypatch.setattr(database.SimulationWorker, "__call__", real)
    copy = tmp_path / "copy" / "db.h5"
    copy.parent.mkdir()
    shutil.copyfile(path, copy)
    with pytest.warns(IncompleteDatabaseWarning, match=r"interrupted database .*db\.h5: 1 of 2 simulations done; "
                                                       r"rerun `toolkit impact database` with the same options"):
        assert load_database(copy).velocities.tolist() == [30.0]
    with pytest.raises(DatabaseError, match=r"empty\.h5: 0 of 1 simulations done; rerun"):
        load_database(tmp_path / "empty.h5")
    report = build_database(path, [30.0, 40.0], [], scene, workers=0, progress=False)
    assert report.done == ["v40"] and report.skipped == ["v30"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        db = load_database(path)
    assert db.velocities.tolist() == [30.0, 40.0] and isinstance(db.index["key"][0], str)


def test_a_database_in_a_missing_folder_is_refused_before_any_simulation(tmp_path, monkeypatch):
    from toolkit.common.training.database import DatabaseError
    from toolkit.impact import database

    def never(self, params):
        raise AssertionError("simulated although the output cannot be written")

    monkeypatch.setattr(database.SimulationWorker, "__call__", never)
    with pytest.raises(DatabaseError, match=r"cannot write next to the database .*nowhere.*db\.h5"):
        build_database(tmp_path / "nowhere" / "db.h5", [30.0], [], tiny_scene(), workers=0, progress=False)
