"""The documentation's benchmark tables are generated from the committed results.

``benchmarks/report.py --check`` must pass on the repository (every block of README.md and
docs/*.md, and docs/benchmarks.md, equals what benchmarks/results gives), and on a tiny fake
tree the check must fail after a result changes and pass again once the pages are regenerated.
"""

import importlib.util
import sys
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"


def _module(name: str):
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))  # report.py and the benchmarks import _provenance as a sibling
    spec = importlib.util.spec_from_file_location(f"benchmarks_{name}", BENCHMARKS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def report():
    return _module("report")


@pytest.fixture(scope="module")
def provenance():
    return _module("_provenance")


def test_repository_pages_match_committed_results(report):
    """Every generated block in README.md and docs/*.md, and docs/benchmarks.md, is up to date:
    run ``python benchmarks/report.py`` after changing a result or a page's blocks."""
    problems = report.run(ROOT, BENCHMARKS / "results", check=True)
    assert problems == [], "\n".join(problems)


def test_results_folder_stays_small():
    """Only small tables are tracked: databases, models and fields go to benchmarks/work/."""
    results = BENCHMARKS / "results"
    files = list(results.glob("*")) if results.exists() else []
    assert all(f.suffix in (".csv", ".json") for f in files), [f.name for f in files]
    assert sum(f.stat().st_size for f in files) < 5 * 2**20


def _fake_tree(tmp_path: Path, provenance) -> Path:
    (tmp_path / "docs").mkdir()
    (tmp_path / "README.md").write_text("# Demo\n\n<!-- results: phantoms -->\nhand-typed\n<!-- /results -->\n\n"
                                        "<!-- results: static_ladder -->\n<!-- /results -->\n")
    (tmp_path / "docs" / "phantom.md").write_text("# Phantom\n\n<!-- results: phantoms -->\n<!-- /results -->\n")
    rows = pd.DataFrame({"phantom": ["face_hex", "face_hex"], "resolution": ["coarse", "paper"],
                         "nodes": [700, 4000], "elements": [480, 3100], "min_scaled_jacobian": [0.61, 0.55],
                         "p01_scaled_jacobian": [0.7, 0.66], "build_s": [0.02, 0.1], "peak_mib": [1.5, 9.0]})
    provenance.write_result(tmp_path / "results" / "phantoms.csv", rows,
                            argv=["benchmarks/phantoms.py", "--repeat", "1"])
    return tmp_path


def test_check_fails_on_a_changed_result_and_passes_after_regeneration(tmp_path, report, provenance, capsys):
    root = _fake_tree(tmp_path, provenance)
    args = ["--root", str(root), "--results", str(root / "results")]
    assert report.main(["--check", *args]) == 1  # hand-typed content, no docs/benchmarks.md yet
    assert report.main(args) == 0
    assert report.main(["--check", *args]) == 0
    readme = (root / "README.md").read_text()
    assert "| face_hex | paper | 4,000 |" in readme
    assert "`python benchmarks/phantoms.py --repeat 1`" in readme  # the command that measured it
    assert "AMD EPYC" in readme or "cores" in readme
    # a missing result is one line with the command that measures it, never a figure
    assert "not measured: run `python benchmarks/static_ladder.py" in readme
    assert "## Phantoms" in (root / "docs" / "benchmarks.md").read_text()

    csv = root / "results" / "phantoms.csv"
    csv.write_text(csv.read_text().replace("4000", "4100"))
    capsys.readouterr()
    assert report.main(["--check", *args]) == 1
    err = capsys.readouterr().err
    assert "README.md: block 'phantoms' differs" in err
    assert "phantom.md: block 'phantoms' differs" in err
    assert "docs/benchmarks.md" in err
    assert report.main(args) == 0
    assert report.main(["--check", *args]) == 0
    assert "| face_hex | paper | 4,100 |" in (root / "docs" / "phantom.md").read_text()


def test_unknown_block_name_is_reported(tmp_path, report, provenance, capsys):
    root = _fake_tree(tmp_path, provenance)
    (root / "docs" / "typo.md").write_text("<!-- results: phantom -->\n<!-- /results -->\n")
    args = ["--root", str(root), "--results", str(root / "results")]
    report.main(args)
    capsys.readouterr()
    assert report.main(["--check", *args]) == 1
    assert "typo.md: unknown block 'phantom'" in capsys.readouterr().err


def test_provenance_records_machine_versions_commit_and_command(tmp_path, provenance):
    path = provenance.write_result(tmp_path / "t.csv", pd.DataFrame({"a": [1]}), argv=["benchmarks/x.py", "--n", "2"],
                                   extra={"size": "coarse"})
    side = provenance.read_sidecar(path)
    prov = side["provenance"]
    assert prov["command"] == "python benchmarks/x.py --n 2"
    assert prov["machine"]["cores"] >= 1 and prov["machine"]["cpu"]
    assert {"python", "numpy", "scipy", "pandas"} <= set(prov["versions"])
    assert len(prov["git"]["commit"]) in (7, 40) or prov["git"]["commit"] == "unknown"
    assert side["extra"] == {"size": "coarse"} and side["runs"][0]["command"] == prov["command"]
    # a resumed benchmark keeps the earlier command beside the new one
    provenance.write_result(path, pd.DataFrame({"a": [1, 2]}), argv=["benchmarks/x.py", "--n", "3"], resumed=True)
    assert [r["command"] for r in provenance.read_sidecar(path)["runs"]] == [
        "python benchmarks/x.py --n 2", "python benchmarks/x.py --n 3"]


def test_every_benchmark_states_the_code_it_measures(report):
    """``--stale`` reads each benchmark's ``MEASURES``: every script states it, with paths that exist."""
    for script in sorted(BENCHMARKS.glob("*.py")):
        if script.name in ("report.py", "_provenance.py"):
            continue
        paths = report.measured_paths(script)
        assert paths, f"{script.name} states no MEASURES"
        missing = [p for p in paths if not (ROOT / p).exists()]
        assert not missing, f"{script.name}: MEASURES names {missing}, which do not exist"


def test_a_result_is_stale_once_the_code_it_measures_changes(report, tmp_path):
    """In a throw-away repository: a result measured on the current commit is fresh; a change to
    a file its benchmark does not measure leaves it fresh; a change to one it measures makes it
    stale, naming the file; a modified tree and an unknown commit are named as such."""
    import json
    import subprocess

    def git(*args):
        return subprocess.run(["git", *args], cwd=tmp_path, check=True, capture_output=True, text=True).stdout.strip()

    git("init", "-q")
    git("config", "user.email", "t@example.org")
    git("config", "user.name", "t")
    (tmp_path / "benchmarks" / "results").mkdir(parents=True)
    (tmp_path / "toolkit").mkdir()
    (tmp_path / "benchmarks" / "speed.py").write_text('MEASURES = ("toolkit/solver.py",)\n')
    (tmp_path / "toolkit" / "solver.py").write_text("x = 1\n")
    (tmp_path / "toolkit" / "other.py").write_text("y = 1\n")
    git("add", "-A")
    git("commit", "-qm", "first")
    first = git("rev-parse", "HEAD")
    results = tmp_path / "benchmarks" / "results"

    def sidecar(name, commit, dirty=False):
        run = {"command": "python benchmarks/speed.py", "commit": commit, "dirty": dirty}
        (results / f"{name}.json").write_text(json.dumps({"name": name, "runs": [run]}))

    sidecar("speed", first)
    assert report.stale_results(tmp_path, results) == []
    (tmp_path / "toolkit" / "other.py").write_text("y = 2\n")
    git("commit", "-qam", "other")
    assert report.stale_results(tmp_path, results) == []
    (tmp_path / "toolkit" / "solver.py").write_text("x = 2\n")
    git("commit", "-qam", "solver")
    assert report.stale_results(tmp_path, results) == [
        f"speed: measured on {first[:9]}; since then toolkit/solver.py changed"]
    sidecar("speed", git("rev-parse", "HEAD"), dirty=True)
    assert report.stale_results(tmp_path, results) == ["speed: measured on a modified tree"]
    sidecar("speed", "0" * 40)
    assert report.stale_results(tmp_path, results) == [
        "speed: commit 000000000 is not in this repository's history"]
