"""Execute the notebooks and store them with their outputs, so a reader sees the figures.

Usage::

    python notebooks/execute.py                      # all notebooks in notebooks/
    python notebooks/execute.py phantoms static_simulation

Each notebook runs top to bottom in a fresh kernel whose working directory is a
temporary folder (the notebooks write their own files into ``tempfile.mkdtemp()``
folders as well), then is written back in place with its outputs. Images are
stored compactly (:func:`shrink_images`), and a notebook larger than
:data:`MAX_BYTES` is reported as an error (exit status 1) but still written, so
the oversized outputs can be inspected. The digest of the code cells is stored in the
notebook's metadata (``toolkit.code_sha256``), so a test can tell stored outputs that
no longer belong to the code. The tests (``tests/test_notebooks.py``)
run the same :func:`execute` on a copy and check the stored files with
:func:`check_stored`.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import io
import sys
import tempfile
import time
from pathlib import Path

NOTEBOOK_DIR = Path(__file__).resolve().parent
#: largest stored notebook, bytes (GitHub renders it, diffs stay readable)
MAX_BYTES = 1_000_000
#: stored PNG outputs wider than this are downscaled, pixels
MAX_IMAGE_WIDTH = 800
#: seconds one cell may run
CELL_TIMEOUT = 900


def notebook_paths(names: list[str] | None = None) -> list[Path]:
    """The notebooks in ``notebooks/``, or those named (stem or file name)."""
    paths = sorted(NOTEBOOK_DIR.glob("*.ipynb"))
    if not names:
        return paths
    by_stem = {p.stem: p for p in paths}
    chosen = []
    for name in names:
        stem = Path(name).stem
        if stem not in by_stem:
            raise ValueError(f"no notebook {name!r} in {NOTEBOOK_DIR}; expected one of {sorted(by_stem)}")
        chosen.append(by_stem[stem])
    return chosen


def execute(nb, cwd: str | Path):
    """Run notebook ``nb`` (an ``nbformat`` node, changed in place) in a fresh kernel working in ``cwd``.

    Raises ``nbclient.exceptions.CellExecutionError`` with the failing cell's traceback.
    """
    import nbclient

    client = nbclient.NotebookClient(nb, timeout=CELL_TIMEOUT, kernel_name="python3", record_timing=False,
                                     resources={"metadata": {"path": str(cwd)}})
    client.execute()
    return nb


def code_digest(nb) -> str:
    """SHA-256 of the notebook's code cells: the stored outputs belong to this code."""
    code = "\n\0".join(c.source for c in nb.cells if c.cell_type == "code")
    return hashlib.sha256(code.encode("utf-8")).hexdigest()


def shrink_images(nb, max_width: int = MAX_IMAGE_WIDTH) -> int:
    """Store the PNG outputs of ``nb`` compactly; returns how many were rewritten.

    Images wider than ``max_width`` pixels are downscaled, and an image is stored with a
    256-colour palette when that makes it smaller (renders and plots have few colours).
    """
    from PIL import Image

    shrunk = 0
    for cell in nb.cells:
        for out in cell.get("outputs", []):
            data = out.get("data", {})
            if "image/png" not in data:
                continue
            raw = base64.b64decode(data["image/png"])
            img = Image.open(io.BytesIO(raw)).convert("RGB")
            if img.width > max_width:
                img = img.resize((max_width, round(img.height * max_width / img.width)), Image.LANCZOS)
            buf = io.BytesIO()
            img.quantize(colors=256, method=Image.Quantize.MEDIANCUT).save(buf, format="PNG", optimize=True)
            if buf.tell() >= len(raw):
                continue
            data["image/png"] = base64.b64encode(buf.getvalue()).decode("ascii")
            out.setdefault("metadata", {}).pop("image/png", None)  # stale width/height
            shrunk += 1
    return shrunk


def drop_widget_warnings(nb) -> int:
    """Remove the stderr lines tqdm writes when ipywidgets is missing; returns how many outputs changed.

    ``tqdm.auto`` warns "IProgress not found" in a kernel without ipywidgets even when
    no progress bar is shown; the warning says nothing about the notebook.
    """
    changed = 0
    for cell in nb.cells:
        if cell.cell_type != "code":
            continue
        kept = []
        for out in cell.outputs:
            if out.output_type == "stream" and out.name == "stderr" and "IProgress not found" in out.text:
                changed += 1
                out.text = "".join(line for line in out.text.splitlines(keepends=True)
                                   if "IProgress not found" not in line and "notebook_tqdm" not in line)
                if not out.text.strip():
                    continue
            kept.append(out)
        cell.outputs = kept
    return changed


def check_stored(path: str | Path) -> list[str]:
    """What is wrong with the stored notebook at ``path``: too large, not executed, outputs of other
    code, no image, an error output. An empty list when nothing is."""
    import nbformat

    path = Path(path)
    problems = []
    size = path.stat().st_size
    if size > MAX_BYTES:
        problems.append(f"{path.name} is {size:,} bytes; expected at most {MAX_BYTES:,}")
    nb = nbformat.read(path, as_version=4)
    code = [c for c in nb.cells if c.cell_type == "code"]
    outputs = [o for c in code for o in c.get("outputs", [])]
    unrun = [i for i, c in enumerate(nb.cells) if c.cell_type == "code" and c.get("execution_count") is None]
    if unrun:
        problems.append(f"{path.name}: code cells {unrun} have not been executed")
    stored_digest = nb.metadata.get("toolkit", {}).get("code_sha256")
    if stored_digest != code_digest(nb):
        problems.append(f"{path.name}: the code changed since the outputs were stored (code_sha256 "
                        f"{stored_digest!r}); run python notebooks/execute.py {path.stem}")
    if not any("image/png" in o.get("data", {}) for o in outputs):
        problems.append(f"{path.name} stores no image/png output; expected at least one figure")
    errors = [o.get("ename", "") for o in outputs if o.output_type == "error"]
    if errors:
        problems.append(f"{path.name} stores error outputs: {errors}")
    return problems


def main(argv: list[str] | None = None) -> int:
    import nbformat

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("names", nargs="*", help="notebook names (default: all in notebooks/)")
    args = parser.parse_args(argv)
    status = 0
    for path in notebook_paths(args.names):
        nb = nbformat.read(path, as_version=4)
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory(prefix=f"{path.stem}-") as cwd:
            execute(nb, cwd)
        shrunk = shrink_images(nb)
        nb.metadata["toolkit"] = {"code_sha256": code_digest(nb)}
        drop_widget_warnings(nb)
        nbformat.write(nb, path)
        problems = check_stored(path)
        print(f"{path.name}: {time.perf_counter() - t0:.0f} s, {path.stat().st_size / 1e3:.0f} kB, "
              f"{shrunk} images compacted")
        for p in problems:
            print(f"  {p}", file=sys.stderr)
        status |= bool(problems)
    return status


if __name__ == "__main__":
    sys.exit(main())
