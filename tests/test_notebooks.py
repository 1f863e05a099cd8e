"""Examples are tests: every notebook in notebooks/ runs top to bottom on coarse meshes,
and is stored with its outputs (at least one figure, under 1 MB) so a reader sees them.

The stored files are refreshed with ``python notebooks/execute.py``; the tests below run
a copy in a temporary folder and never rewrite them.
"""

import importlib.util
from pathlib import Path

import pytest

NOTEBOOK_DIR = Path(__file__).resolve().parents[1] / "notebooks"
NOTEBOOKS = sorted(NOTEBOOK_DIR.glob("*.ipynb"))


def _execute_module():
    spec = importlib.util.spec_from_file_location("notebooks_execute", NOTEBOOK_DIR / "execute.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.long
@pytest.mark.notebook
@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs(path, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    pytest.importorskip("nbclient")
    stored = path.read_bytes()
    nb = nbformat.read(path, as_version=4)
    _execute_module().execute(nb, tmp_path)  # raises CellExecutionError with the failing cell's traceback
    errors = [o for c in nb.cells if c.cell_type == "code" for o in c.get("outputs", []) if o.output_type == "error"]
    assert not errors
    assert path.read_bytes() == stored, f"running {path.name} rewrote the stored file"
    # the kernel worked in tmp_path: a file there would land beside the notebook in Jupyter
    written = sorted(p.name for p in tmp_path.iterdir())
    assert not written, f"{path.name} wrote {written} into its working directory; expected tempfile.mkdtemp()"


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_is_stored_with_figures(path):
    """Executed from its current code, with an image, no error output, under 1 MB (``python notebooks/execute.py``)."""
    pytest.importorskip("nbformat")
    assert _execute_module().check_stored(path) == []


def test_execute_names_select_notebooks():
    execute = _execute_module()
    assert execute.notebook_paths() == NOTEBOOKS
    assert execute.notebook_paths(["phantoms.ipynb"]) == [NOTEBOOK_DIR / "phantoms.ipynb"]
    with pytest.raises(ValueError, match="no notebook 'nope'"):
        execute.notebook_paths(["nope"])
