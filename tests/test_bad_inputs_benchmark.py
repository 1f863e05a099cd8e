"""The bad-input benchmark's judge: what counts as a clear error, on two real commands."""

import importlib.util
import sys
from pathlib import Path

BENCHMARKS = Path(__file__).resolve().parent.parent / "benchmarks"


def _module():
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))
    spec = importlib.util.spec_from_file_location("benchmarks_bad_inputs", BENCHMARKS / "bad_inputs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def test_judge_rule():
    bad = _module()
    line, as_option, why = bad.judge(2, "error: plans = 0; expected an integer >= 1\n", ["--plans"])
    assert why == "" and not as_option  # the option's word counts, the option as typed is told apart
    _, _, why = bad.judge(1, "Traceback (most recent call last):\nValueError: x\n", ["face.inp"])
    assert "exit 1" in why and "traceback" in why and "0 error lines" in why
    _, _, why = bad.judge(2, "error: mesh.nodes: stored 771, asked 4100\n", ["--resolution"])
    assert why.startswith("does not name")


def test_two_catalogue_cases_run():
    bad = _module()
    cases = {(c.command, c.case): c for c in bad.catalogue()}
    for key in (("static simulate", "--threads 0"), ("phantom", "unknown suffix")):
        row = bad.run_case(cases[key])
        assert row["clear"], row
        assert row["exit_code"] == 2 and not row["left_files"], row
