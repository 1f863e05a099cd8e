"""The API reference (``docs/api.md``) is generated from the code and says something of every
public name: it matches what ``python docs/make_api.py`` writes, and every exported class and
function has a docstring."""

import importlib
import importlib.util
import inspect
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def make_api():
    spec = importlib.util.spec_from_file_location("make_api", ROOT / "docs" / "make_api.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_page_matches_the_code(make_api):
    assert (ROOT / "docs" / "api.md").read_text() == make_api.render(), "run python docs/make_api.py"


def test_every_public_class_and_function_has_a_docstring(make_api):
    bare = [f"{package}.{name}" for package in make_api.PACKAGES
            for name in importlib.import_module(package).__all__
            if (inspect.isclass(obj := getattr(importlib.import_module(package), name)) or inspect.isfunction(obj))
            and not make_api._first_paragraph(obj)]
    assert bare == []


def test_check_fails_on_a_stale_page(make_api, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(make_api, "OUT", tmp_path / "api.md")
    (tmp_path / "api.md").write_text("# API reference\n\nstale\n")
    assert make_api.main(["--check"]) == 1
    assert "differs from the code" in capsys.readouterr().err
    assert make_api.main([]) == 0 and make_api.main(["--check"]) == 0
