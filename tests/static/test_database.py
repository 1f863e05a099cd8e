"""The static learning database: one sample per increment of sampled plans on phantom
subjects, crash-safe and resumable generation, clear refusal of foreign files."""

import importlib
import json
import shutil
import warnings
from concurrent.futures import Future

import h5py
import numpy as np
import pandas.testing as pd_testing
import pytest

from toolkit.common.training.database import DatabaseError, IncompleteDatabaseWarning
from toolkit.static.database import DatabaseConfig, StaticDatabase, build_database, read_samples

database_module = importlib.import_module("toolkit.static.database")
CONFIG = DatabaseConfig(resolution="coarse", subjects=2, plans=2, seed=3)


@pytest.fixture(scope="module")
def small_db(tmp_path_factory):
    path = tmp_path_factory.mktemp("db") / "db.h5"
    report = build_database(path, CONFIG, workers=0, progress=False)
    assert len(report.done) == 4 and not report.failed
    return path


def test_samples_are_increments_with_exact_inputs(small_db):
    """Every increment of every simulation is a sample (2 subjects x 2 plans x 3 increments):
    the starting mesh is the pre-operative face plus the previous increments, the moving
    nodes' prescribed displacement equals their FE displacement exactly (float32 storage),
    fixed nodes do not move, and the two subjects have different faces with the same
    topology. The per-increment table has the plan parameters and diagnostics, and the
    per-simulation index is readable with pandas alone."""
    import pandas as pd

    db = StaticDatabase.open(small_db)
    assert len(db) == 12 and sorted(db.samples.subject.unique()) == [0, 1]
    assert not np.allclose(db.points[0], db.points[1]) and db.points[0].shape == db.points[1].shape
    for i in range(len(db)):
        s = db.sample(i)
        moving, fixed = s["types"] == 1, s["types"] == 2
        assert np.abs(s["s"][moving] - s["v"][moving]).max() < 1e-5
        assert np.all(s["s"][~moving] == 0) and np.all(s["v"][fixed] == 0)
        k = int(s["row"].increment)
        if k > 1:
            prev = db.sample(i - 1)
            np.testing.assert_allclose(s["x"], prev["x"] + prev["v"], atol=1e-5)
    table = read_samples(small_db)
    for col in ("subject", "plan", "increment", "lefort_ty", "distal_rx", "max_input_displacement_mm", "seconds",
                "min_scaled_jacobian", "status"):
        assert col in table.columns
    assert (table.status == "ok").all() and table.max_input_displacement_mm.gt(0).all()
    with h5py.File(small_db) as f:
        index = pd.DataFrame(f["index"][()])
    assert len(index) == 4 and {"seconds", "jaw_closing_mm"} <= set(index.columns)


def test_each_simulation_keeps_the_boundary_types_it_ran_with(small_db, tmp_path):
    """A plan that needed a wider release band or freed cut nodes ran with other boundary types than
    its subject's: its record keeps them and its samples use them (here one record's types are
    changed by hand, as such a retry changes them); records without types read the subject's."""
    with h5py.File(small_db) as f:
        keys = sorted(f["records"])
        for key in keys:
            subject = json.loads(f["records"][key].attrs["params"])["subject"]
            own, shared = f["records"][key]["types"][()], f["shared"][f"subject_{subject:03d}"]["types"][()]
            np.testing.assert_array_equal(own, shared)
    copy = tmp_path / "retried.h5"
    shutil.copy(small_db, copy)
    with h5py.File(copy, "r+") as f:
        types = f["records"][keys[0]]["types"]
        moving = np.flatnonzero(types[()] == 1)[:3]
        changed = types[()]
        changed[moving] = 0  # released: free
        types[...] = changed
        del f["records"][keys[1]]["types"]
    db = StaticDatabase.open(copy)
    first = db.samples.index[db.samples.key == keys[0]][0]
    second = db.samples.index[db.samples.key == keys[1]][0]
    assert np.all(db.sample(first)["types"][moving] == 0) and np.all(db.sample(first)["s"][moving] == 0)
    np.testing.assert_array_equal(db.sample(second)["types"], db.types[int(db.samples.subject[second])])


def test_rerun_resumes_and_an_interrupted_run_gives_the_same_database(small_db, tmp_path):
    """A rerun skips the 4 finished simulations. A run interrupted (Ctrl-C) after its second
    simulation keeps those two in the .h5 itself (a copy of the file alone opens, with its 6
    samples and a warning "interrupted database ...: 2 of 4 simulations done; rerun ..."); the
    rerun does the other two, and the database then equals the uninterrupted one (every array
    identical) and opens without a warning."""
    again = build_database(small_db, CONFIG, workers=0, progress=False)
    assert not again.done and len(again.skipped) == 4

    class Interrupting:
        def __init__(self):
            self.calls = 0

        def submit(self, fn, *args):
            self.calls += 1
            if self.calls == 3:
                raise KeyboardInterrupt
            fut = Future()
            fut.set_result(fn(*args))
            return fut

    path = tmp_path / "cut.h5"
    with pytest.raises(KeyboardInterrupt):
        build_database(path, CONFIG, executor=Interrupting(), progress=False)
    from toolkit.common.training.database import Database

    assert len(Database(path, database_module.DATABASE_KIND, database_module.DATABASE_VERSION, CONFIG.to_dict())
               .keys()) == 2
    copy = tmp_path / "copy" / "cut.h5"
    copy.parent.mkdir()
    shutil.copyfile(path, copy)
    with pytest.warns(IncompleteDatabaseWarning, match=r"interrupted database .*cut\.h5: 2 of 4 simulations done; "
                                                       r"rerun `toolkit static database` with the same options"):
        partial = StaticDatabase.open(copy)
    assert len(partial) == 6
    report = build_database(path, CONFIG, workers=0, progress=False)
    assert len(report.done) == 2 and len(report.skipped) == 2
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        a, b = StaticDatabase.open(small_db), StaticDatabase.open(path)
    assert list(a.samples.key) == list(b.samples.key)
    for key in a.samples.key.unique():
        np.testing.assert_array_equal(a._U[key], b._U[key])


def test_an_interrupt_before_any_simulation_leaves_a_database_that_says_so(tmp_path, monkeypatch):
    """Ctrl-C during the first simulation: opening the file is refused with "0 of 2 simulations
    done; rerun ... to finish it" (not "has no /samples table")."""
    def interrupted(params):
        raise KeyboardInterrupt

    monkeypatch.setattr(database_module, "simulate_job", interrupted)
    path = tmp_path / "empty.h5"
    with pytest.raises(KeyboardInterrupt):
        build_database(path, DatabaseConfig(resolution="coarse", plans=2), workers=0, progress=False)
    with pytest.raises(DatabaseError, match=r"interrupted database .*empty\.h5: 0 of 2 simulations done; rerun"):
        StaticDatabase.open(path)


def test_more_plans_and_subjects_grow_the_database_with_the_same_first_ones(small_db, tmp_path):
    """3 plans on the 2-plan database: the 4 finished simulations are kept (arrays unchanged) and
    only the third plan of each subject runs; its plan is the one a fresh 3-plan database draws
    (plan p depends only on seed, subject and p), and the file records 3 plans. A third subject
    then adds its face and plans."""
    grown = tmp_path / "grown.h5"
    shutil.copyfile(small_db, grown)
    bigger = DatabaseConfig(resolution="coarse", subjects=2, plans=3, seed=3)
    report = build_database(grown, bigger, workers=0, progress=False)
    assert sorted(report.done) == ["s000-p00002", "s001-p00002"] and len(report.skipped) == 4
    a, b = StaticDatabase.open(small_db), StaticDatabase.open(grown)
    assert b.config == bigger and len(b) == 18
    for key in a.samples.key.unique():
        np.testing.assert_array_equal(a._U[key], b._U[key])
    fresh = {job.key: job.params["motions"] for job in database_module._jobs(bigger)}
    with h5py.File(grown) as f:
        for key, motions in fresh.items():
            assert json.loads(f["records"][key].attrs["params"])["motions"] == motions
    # a smaller run afterwards keeps everything and the record of 3 plans
    assert len(build_database(grown, CONFIG, workers=0, progress=False).skipped) == 4
    assert StaticDatabase.open(grown).config.plans == 3
    # a third subject: its face and its 3 plans are added, the rest kept
    more = DatabaseConfig(resolution="coarse", subjects=3, plans=3, seed=3)
    report = build_database(grown, more, workers=0, progress=False)
    assert sorted(report.done) == [f"s002-p{p:05d}" for p in range(3)] and len(report.skipped) == 6
    c = StaticDatabase.open(grown)
    assert c.config == more and len(c) == 27 and sorted(c.points) == [0, 1, 2]
    np.testing.assert_array_equal(c.points[2], database_module.subject_phantom("coarse", 2).mesh.points)
    np.testing.assert_array_equal(c.points[1], b.points[1])


def test_samples_are_rebuilt_from_the_records_when_the_table_is_missing_or_stale(small_db, tmp_path):
    """A file whose /samples table was never written (killed before it) or lags its records reads
    the same per-increment table, rebuilt from the records; its string columns are str."""
    ref = read_samples(small_db)
    for name in ("missing.h5", "stale.h5"):
        path = tmp_path / name
        shutil.copyfile(small_db, path)
        with h5py.File(path, "a") as f:
            if name == "missing.h5":
                del f["samples"]
            else:
                rows = f["samples"][()]
                del f["samples"]
                f.create_dataset("samples", data=rows[:3])
        pd_testing.assert_frame_equal(read_samples(path), ref)
    assert isinstance(ref.key[0], str) and isinstance(ref.status[0], str)


def test_failures_are_recorded_and_foreign_files_refused(tmp_path, monkeypatch):
    """A simulation that raises is recorded with its reason, listed in /samples as failed and
    skipped on the next run; a corrupt file, a database of another kind and one made with
    another configuration are refused naming the problem."""
    real = database_module.simulate_job

    def flaky(params):
        if params["plan"] == 1:
            raise RuntimeError("inverted elements (test)")
        return real(params)

    monkeypatch.setattr(database_module, "simulate_job", flaky)
    cfg = DatabaseConfig(resolution="coarse", plans=2)
    path = tmp_path / "f.h5"
    report = build_database(path, cfg, workers=0, progress=False)
    assert list(report.failed) == ["s000-p00001"] and "inverted elements (test)" in report.failed["s000-p00001"]
    table = read_samples(path)
    assert table.status.str.startswith("failed").sum() == 1
    assert len(build_database(path, cfg, workers=0, progress=False).skipped) == 2
    with pytest.raises(ValueError, match="increments: stored 3, asked 2"):
        build_database(path, DatabaseConfig(resolution="coarse", plans=2, increments=2), workers=0, progress=False)
    (tmp_path / "junk.h5").write_bytes(b"not hdf5 at all")
    with pytest.raises(DatabaseError, match="cannot read"):
        StaticDatabase.open(tmp_path / "junk.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f.attrs["format"] = "toolkit.impact.database"
        f.attrs["format_version"] = 1
    with pytest.raises(DatabaseError, match="is not a 'toolkit.static.database' database"):
        StaticDatabase.open(tmp_path / "other.h5")


def test_dask_local_cluster_fills_the_same_database(small_db, tmp_path):
    """Generation on a dask.distributed LocalCluster (the documented way to scale out) gives the
    same samples as local generation, array for array."""
    distributed = pytest.importorskip("distributed")
    path = tmp_path / "dask.h5"
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        report = build_database(path, CONFIG, executor=client, progress=False)
    assert len(report.done) == 4
    a, b = StaticDatabase.open(small_db), StaticDatabase.open(path)
    for key in a.samples.key.unique():
        np.testing.assert_array_equal(a._U[key], b._U[key])
