"""The resumable HDF5 job database: records and failures land in the file, the index is readable
with h5py + pandas alone, reruns skip what is done (and failed, unless retried), an interrupted
run keeps every finished job, leftover shards are merged, and foreign, mismatched or corrupt
files are refused with a message naming the problem."""

import os
import re
import shutil
import signal
from concurrent.futures import ThreadPoolExecutor

import h5py
import numpy as np
import pandas as pd
import pytest

from toolkit.common.config_diff import IncompatibleError
from toolkit.common.training.database import (
    Database,
    DatabaseError,
    IncompleteDatabaseWarning,
    Job,
    Record,
    check_complete,
    database_status,
    read_failures,
    read_index,
    run_jobs,
)

KIND = "toolkit.test.database"


def square(params):
    """A worker: arrays depend on the params; x = 3 fails."""
    x = params["x"]
    if x == 3:
        raise RuntimeError("x = 3 is not allowed")
    return Record({"values": np.arange(4.0) * x, "grid": np.full((2, 2), x)}, {"sum": 6.0 * x, "label": f"x{x}"})


def _db(tmp_path, config=None):
    db = Database(tmp_path / "db.h5", KIND, 1, config or {"grid": 2})
    db.create(shared={"points": np.eye(3)})
    return db


def _jobs(xs):
    return [Job(f"x{x}", {"x": x}) for x in xs]


def test_records_failures_and_the_plain_pandas_index(tmp_path):
    """Three jobs in this process: two records with their arrays and attributes, one failure with
    its reason; the index table has one row per record (key, params, attributes) and reads with
    h5py + pandas only."""
    db = _db(tmp_path)
    report = run_jobs(db, _jobs([1, 2, 3]), square, workers=0, progress=False)
    assert sorted(report.done) == ["x1", "x2"] and list(report.failed) == ["x3"]
    assert "RuntimeError: x = 3 is not allowed" in report.failed["x3"]
    with h5py.File(db.path) as f:
        np.testing.assert_array_equal(f["records/x2/values"][()], [0.0, 2.0, 4.0, 6.0])
        np.testing.assert_array_equal(f["shared/points"][()], np.eye(3))
        plain = pd.DataFrame(f["index"][()])
    assert sorted(plain["x"]) == [1, 2] and sorted(plain["sum"]) == [6.0, 12.0]
    table = read_index(db.path)
    assert set(table["key"]) == {"x1", "x2"} and set(table["label"]) == {"x1", "x2"}
    fails = read_failures(db.path)
    assert list(fails["key"]) == ["x3"] and "not allowed" in fails["reason"][0]
    assert not db.shards.exists()  # merged


def test_rerun_skips_done_and_failed_jobs_unless_retried(tmp_path):
    db = _db(tmp_path)
    run_jobs(db, _jobs([1, 3]), square, workers=0, progress=False)
    again = run_jobs(db, _jobs([1, 3, 4]), square, workers=0, progress=False)
    assert again.done == ["x4"] and sorted(again.skipped) == ["x1", "x3"]
    retry = run_jobs(db, _jobs([1, 3, 4]), square, workers=0, retry_failed=True, progress=False)
    assert list(retry.failed) == ["x3"] and sorted(retry.skipped) == ["x1", "x4"]


def test_any_executor_works(tmp_path):
    """A thread pool (any concurrent.futures executor) gives the same records as in-process runs."""
    db = _db(tmp_path)
    with ThreadPoolExecutor(2) as pool:
        report = run_jobs(db, _jobs([1, 2, 4]), square, executor=pool, progress=False)
    assert sorted(report.done) == ["x1", "x2", "x4"]
    assert sorted(read_index(db.path)["sum"]) == [6.0, 12.0, 24.0]


def test_dask_local_cluster(tmp_path):
    """A dask.distributed Client on a LocalCluster is accepted as the executor (its
    get_executor() is used) and fills the same database."""
    distributed = pytest.importorskip("distributed")
    db = _db(tmp_path)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as cl, \
            distributed.Client(cl) as client:
        report = run_jobs(db, _jobs([1, 2, 3]), square, executor=client, progress=False)
    assert sorted(report.done) == ["x1", "x2"] and list(report.failed) == ["x3"]
    assert sorted(read_index(db.path)["x"]) == [1, 2]


def test_interrupt_keeps_finished_jobs_and_leftover_shards_are_merged(tmp_path):
    """Ctrl-C during the third job: the two finished records are in the file afterwards, and the
    next run does only the rest. A shard left by a killed run (never merged) is merged at the next
    start instead of being recomputed."""
    db = _db(tmp_path)

    def interrupting(params):
        if params["x"] == 5:
            raise KeyboardInterrupt
        return square(params)

    with pytest.raises(KeyboardInterrupt):
        run_jobs(db, _jobs([1, 2, 5, 6]), interrupting, workers=0, progress=False)
    assert db.keys() == ["x1", "x2"]
    db.write_shard(Job("x7", {"x": 7}), "done", square({"x": 7}), [])  # as if killed before merging
    report = run_jobs(db, _jobs([1, 2, 5, 6, 7]), square, workers=0, progress=False)
    assert sorted(report.done) == ["x5", "x6"] and sorted(report.skipped) == ["x1", "x2", "x7"]
    assert sorted(read_index(db.path)["x"]) == [1, 2, 5, 6, 7]


def test_foreign_mismatched_and_corrupt_files_are_refused(tmp_path):
    _db(tmp_path, {"grid": 2})
    with pytest.raises(IncompatibleError, match=r"grid: stored 2, asked 3"):
        Database(tmp_path / "db.h5", KIND, 1, {"grid": 3}).create()
    with pytest.raises(DatabaseError, match="is not a 'other.kind' database"):
        Database(tmp_path / "db.h5", "other.kind", 1, {"grid": 2}).create()
    with pytest.raises(DatabaseError, match="format version 1, this toolkit reads version 2"):
        Database(tmp_path / "db.h5", KIND, 2, {"grid": 2}).create()
    bad = tmp_path / "bad.h5"
    bad.write_bytes(b"not an hdf5 file at all")
    with pytest.raises(DatabaseError, match="cannot read .*bad.h5 as HDF5"):
        Database(bad, KIND, 1, {}).create()
    with pytest.raises(ValueError, match="must be unique"):
        run_jobs(_db(tmp_path), _jobs([1, 1]), square, workers=0, progress=False)
    with pytest.raises(ValueError, match="job key 'a/b'"):
        Job("a/b")


def interrupting(params):
    """A worker interrupted (Ctrl-C) on x = 5."""
    if params["x"] == 5:
        raise KeyboardInterrupt
    return square(params)


def test_an_interrupted_h5_alone_holds_the_finished_jobs_and_says_how_far_it_got(tmp_path):
    """Ctrl-C on the third of four jobs: no shard is left behind, a copy of the .h5 alone holds
    the two finished records, and its status reads "interrupted database FILE: 2 of 4
    simulations done; rerun ... to finish it" (a warning when used). The rerun finishes it."""
    db = _db(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_jobs(db, _jobs([1, 2, 5, 6]), interrupting, workers=0, progress=False)
    assert not db.shards.exists()
    copy = tmp_path / "copy" / "db.h5"
    copy.parent.mkdir()
    shutil.copyfile(db.path, copy)
    status = database_status(copy)
    assert (status.done, status.planned, status.complete) == (2, 4, False)
    assert sorted(read_index(copy)["key"]) == ["x1", "x2"]
    expected = r"interrupted database .*db\.h5: 2 of 4 simulations done; rerun `make db` to finish it"
    assert re.fullmatch(expected, status.message("`make db`"))
    with pytest.warns(IncompleteDatabaseWarning, match=expected):
        check_complete(copy, "`make db`")
    run_jobs(db, _jobs([1, 2, 5, 6]), square, workers=0, progress=False)
    status = database_status(db.path)
    assert (status.done, status.planned, status.complete) == (4, 4, True)


def test_an_interrupt_before_any_record_is_refused_when_used(tmp_path):
    db = _db(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        run_jobs(db, _jobs([5, 6]), interrupting, workers=0, progress=False)
    with pytest.raises(DatabaseError, match=r"0 of 2 simulations done; rerun `make db` to finish it"):
        check_complete(db.path, "`make db`")


def test_a_second_ctrl_c_during_the_final_merge_waits_for_it(tmp_path, monkeypatch):
    """A SIGINT arriving while the finished shards are merged is held until the merge is done:
    the records are in the .h5 and the KeyboardInterrupt still reaches the caller."""
    db = _db(tmp_path)
    real_merge = Database.merge
    calls = []

    def merge_then_interrupted(self):
        calls.append(1)
        if len(calls) == 2:  # the final merge (the first one is the start's)
            os.kill(os.getpid(), signal.SIGINT)
        return real_merge(self)

    monkeypatch.setattr(Database, "merge", merge_then_interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_jobs(db, _jobs([1, 2]), square, workers=0, progress=False)
    assert not db.shards.exists() and sorted(read_index(db.path)["key"]) == ["x1", "x2"]


def test_string_columns_of_the_index_read_as_str(tmp_path):
    """read_index gives str keys and labels; so does the documented h5py + pandas recipe."""
    db = _db(tmp_path)
    run_jobs(db, _jobs([1, 2]), square, workers=0, progress=False)
    table = read_index(db.path)
    assert all(isinstance(v, str) for v in [*table["key"], *table["label"]])
    with h5py.File(db.path) as f:
        index = pd.DataFrame(f["index"][()])
    index = index.apply(lambda c: c.str.decode("utf-8") if c.dtype == object else c)
    assert sorted(index["key"]) == ["x1", "x2"] and sorted(index["label"]) == ["x1", "x2"]


def test_read_index_reads_any_table_of_the_file_with_str_strings(tmp_path):
    """Another table of the file (a static database's /samples) reads the same way; a name that
    is not a table is refused, listing the tables."""
    db = _db(tmp_path)
    run_jobs(db, _jobs([1]), square, workers=0, progress=False)
    rows = np.array([("x1", 1), ("x1", 2)], dtype=[("key", h5py.string_dtype()), ("increment", np.int64)])
    with h5py.File(db.path, "a") as f:
        f.create_dataset("samples", data=rows)
    samples = read_index(db.path, "samples")
    assert samples["key"].tolist() == ["x1", "x1"] and samples["increment"].tolist() == [1, 2]
    with pytest.raises(DatabaseError, match=r"no table 'records'.*\['index', 'samples'\]"):
        read_index(db.path, "records")


def test_interrupt_after_sends_a_ctrl_c_after_the_given_stored_job(tmp_path):
    """interrupt_after("job", 2): a SIGINT right after the second stored job (a failed one counts),
    on any machine; the run keeps those two and stops; the trigger is then spent, and a rerun
    finishes. A unit or count it does not know is refused."""
    from toolkit.common.runtime import interrupt_after

    db = _db(tmp_path)
    # a shell without job control starts background commands with SIGINT ignored: handle it here as
    # an interactive Python does, whatever started the suite
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    interrupt_after("job", 2)
    try:
        with pytest.raises(KeyboardInterrupt):
            run_jobs(db, _jobs([1, 3, 4, 6]), square, workers=0, progress=False)
    finally:
        interrupt_after("job", None)
        signal.signal(signal.SIGINT, before)
    assert db.keys() == ["x1"] and list(db.failures()) == ["x3"]
    report = run_jobs(db, _jobs([1, 3, 4, 6]), square, workers=0, progress=False)
    assert sorted(report.done) == ["x4", "x6"]
    with pytest.raises(ValueError, match=r"unit = 'epoch'; expected one of \['job', 'frame', 'increment'\]"):
        interrupt_after("epoch", 1)
    with pytest.raises(ValueError, match="count = 0; expected an integer >= 1"):
        interrupt_after("job", 0)


def test_a_sigterm_stops_the_run_like_a_ctrl_c_and_keeps_the_finished_jobs(tmp_path):
    """A SIGTERM (a cluster's time limit) during the third job: KeyboardInterrupt, and the two
    finished records are merged into the .h5; the SIGTERM handler is restored afterwards."""
    db = _db(tmp_path)
    before = signal.getsignal(signal.SIGTERM)

    def terminated(params):
        if params["x"] == 5:
            os.kill(os.getpid(), signal.SIGTERM)
        return square(params)

    with pytest.raises(KeyboardInterrupt, match="SIGTERM"):
        run_jobs(db, _jobs([1, 2, 5, 6]), terminated, workers=0, progress=False)
    assert not db.shards.exists() and sorted(read_index(db.path)["key"]) == ["x1", "x2"]
    assert signal.getsignal(signal.SIGTERM) is before


def test_a_second_run_on_the_same_database_is_refused_while_the_first_runs(tmp_path):
    """While a run holds the database (here: the first run's worker starts a second run on it),
    the second is refused naming the file, and the status reads "being filled by another
    process" rather than "interrupted"; the lock is gone afterwards. A database in a folder that
    does not exist is refused naming the folder's problem."""
    db = _db(tmp_path)
    seen = {}

    def nested(params):
        if params["x"] == 2:
            import subprocess
            import sys

            code = ("import sys\n"
                    "from toolkit.common.training.database import Database, Job, Record, database_status, run_jobs\n"
                    f"db = Database({str(db.path)!r}, {KIND!r}, 1, {{'grid': 2}})\n"
                    "print(database_status(db.path).message())\n"
                    "try:\n    run_jobs(db, [Job('x9', {'x': 9})], print, workers=0, progress=False)\n"
                    "except Exception as exc:\n    print(type(exc).__name__, exc)\n")
            seen["out"] = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
        return square(params)

    run_jobs(db, _jobs([1, 2]), nested, workers=0, progress=False)
    assert re.search(r"database .*db\.h5 is being filled by another process: \d of 2 simulations done so far",
                     seen["out"])
    assert re.search(r"DatabaseError database .*db\.h5 is being filled by another process", seen["out"])
    assert not (tmp_path / "db.h5.lock").exists() and database_status(db.path).complete
    with pytest.raises(DatabaseError, match=r"cannot write next to the database .*nowhere"):
        run_jobs(Database(tmp_path / "nowhere" / "db.h5", KIND, 1, {}), _jobs([1]), square, workers=0,
                 progress=False)
