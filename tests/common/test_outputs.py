"""Output locations are refused before any computation when they cannot be written."""

import os

import pytest

from toolkit.common.errors import ToolkitError
from toolkit.common.outputs import OutputError, check_output_dir, check_output_file


def test_a_new_or_existing_folder_is_accepted_and_nothing_is_created(tmp_path):
    assert check_output_dir(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    assert check_output_dir(tmp_path) == tmp_path
    assert check_output_file(tmp_path / "new" / "db.h5") == tmp_path / "new" / "db.h5"
    assert list(tmp_path.iterdir()) == []  # the probe file is gone, no folder made


def test_an_existing_file_where_a_folder_is_expected(tmp_path):
    (tmp_path / "face.inp").write_text("x")
    with pytest.raises(OutputError, match=r"output folder '.*face.inp' is an existing file; expected a folder.*--out"):
        check_output_dir(tmp_path / "face.inp")
    with pytest.raises(OutputError, match=r"model directory '.*face.inp/model' cannot be created: '.*face.inp' is a "
                                          r"file, not a folder"):
        check_output_dir(tmp_path / "face.inp" / "model", what="model directory")


def test_an_existing_folder_where_a_file_is_expected(tmp_path):
    with pytest.raises(OutputError, match=r"database file '.*' is an existing folder; expected a file name"):
        check_output_file(tmp_path, what="database file")


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="needs /proc (a folder that takes no new files)")
def test_a_folder_that_takes_no_new_files():
    with pytest.raises(OutputError, match=r"output folder '/proc/x' cannot be written: '/proc' does not take new "
                                          r"files .*give a writable out= \(command line: --out\)"):
        check_output_dir("/proc/x")
    with pytest.raises(OutputError, match="'/proc' does not take new files"):
        check_output_file("/proc/x/db.h5")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_folder(tmp_path):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o500)
    try:
        with pytest.raises(OutputError, match="does not take new files"):
            check_output_dir(ro / "out")
    finally:
        ro.chmod(0o700)


def test_output_error_is_a_toolkit_value_error():
    assert issubclass(OutputError, ToolkitError) and issubclass(OutputError, ValueError)


def test_an_interrupted_training_is_not_overwritten_without_resume(tmp_path):
    """checkpoint.pt without model.pt is an interrupted training: refused unless resuming; a
    finished one (model.pt) may be trained over."""
    from toolkit.common.outputs import check_model_dir

    (tmp_path / "checkpoint.pt").write_bytes(b"x")
    with pytest.raises(OutputError, match=r"interrupted training .*\(command line: --resume\)"):
        check_model_dir(tmp_path, resume=False)
    assert check_model_dir(tmp_path, resume=True) == tmp_path
    (tmp_path / "model.pt").write_bytes(b"x")
    assert check_model_dir(tmp_path, resume=False) == tmp_path
