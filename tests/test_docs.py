"""Examples are tests: every ```python and ```bash block of README.md and docs/*.md runs.

The rules (one test per Markdown file):

- the python blocks of a file run in order in one namespace, in a fresh Python process
  whose working directory is a new temporary folder; the bash blocks run there too, in
  document order among the python blocks, with ``bash -e`` and the venv's ``bin`` first
  on ``PATH`` (so ``toolkit`` and ``python`` are the installed ones);
- a block whose fence is preceded, on the line just before, by
  ``<!-- norun: REASON -->`` is not run; a ``norun`` without a reason is an error;
- a block preceded by ``<!-- file: NAME -->`` (e.g. a ```toml plan) is written to
  ``NAME`` in the working directory, for the blocks after it;
- other fences (```text, ```console, ```toml without a file marker) are not run; a
  fence written ```py, ```sh or ```shell (an alias of a run language) without a marker
  is an error, so that no example is left unrun by a spelling.

A failing block fails the test with the Markdown file, the block's line number and the
error (python tracebacks carry the Markdown file's own line numbers).

Run as a script, this file executes one Markdown file's blocks in the current directory:
``python tests/test_docs.py run README.md`` (that is what each test does, in a
subprocess, so that ``set_threads``, ``chdir`` or imports in the examples do not leak
into the test session).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
import traceback
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: seconds all the blocks of one Markdown file may take
TIMEOUT = 900
RUN_LANGUAGES = ("python", "bash")
#: fence languages a reader takes for runnable code but the harness would not run
ALIASES = {"py": "python", "python3": "python", "ipython": "python", "sh": "bash", "shell": "bash", "zsh": "bash"}

_FENCE = re.compile(r"^(?P<indent> *)(?P<fence>`{3,}|~{3,})(?P<info>.*)$")
_MARKER = re.compile(r"^\s*<!--\s*(?P<kind>norun|file)\b\s*(?P<colon>:?)\s*(?P<value>.*?)\s*-->\s*$")


@dataclass(frozen=True)
class Block:
    """One fenced block of a Markdown file.

    Attributes
    ----------
    line : 1-based line of the opening fence
    language : first word of the fence's info string ("" when none)
    code : the block's text (dedented by the fence's indentation), ending with a newline
    action : "python" or "bash" (run), "file" (written to ``file_name``), "skip"
    file_name : target of a ``<!-- file: NAME -->`` marker
    reason : the REASON of a ``<!-- norun: REASON -->`` marker
    """

    line: int
    language: str
    code: str
    action: str
    file_name: str | None = None
    reason: str | None = None


def parse_blocks(text: str, source: str = "<markdown>") -> list[Block]:
    """The fenced blocks of Markdown ``text``, with what to do with each.

    Raises ValueError (naming ``source`` and the line) for a fence that is never
    closed, a ``norun`` marker without a reason or a ``file`` marker without a name.
    """
    lines = text.splitlines()
    blocks = []
    i = 0
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start, indent, fence = i, len(m["indent"]), m["fence"]
        words = m["info"].strip().split()
        language = words[0].strip("{}.").lower() if words else ""
        body = []
        i += 1
        while i < len(lines):
            close = _FENCE.match(lines[i])
            if close and close["fence"].startswith(fence) and not close["info"].strip():
                break
            body.append(lines[i][indent:] if lines[i][:indent].strip() == "" else lines[i].lstrip())
            i += 1
        else:
            raise ValueError(f"{source}:{start + 1}: the fence {fence}{language} is never closed; "
                             f"expected a closing {fence}")
        i += 1
        code = "\n".join(body) + "\n"
        marker = _MARKER.match(lines[start - 1]) if start > 0 else None
        if marker is None:
            if language in ALIASES:
                raise ValueError(f"{source}:{start + 1}: fence {fence}{language} is not run; write {fence}"
                                 f"{ALIASES[language]} to run it, or put <!-- norun: REASON --> on the line before")
            action = language if language in RUN_LANGUAGES else "skip"
            blocks.append(Block(start + 1, language, code, action))
        elif marker["kind"] == "norun":
            if not marker["colon"] or not marker["value"]:
                raise ValueError(f"{source}:{start}: {lines[start - 1].strip()!r} gives no reason; "
                                 "expected <!-- norun: REASON -->, e.g. <!-- norun: 20-minute paper benchmark -->")
            blocks.append(Block(start + 1, language, code, "skip", reason=marker["value"]))
        else:
            name = marker["value"]
            if not marker["colon"] or not name:
                raise ValueError(f"{source}:{start}: {lines[start - 1].strip()!r} gives no file name; "
                                 "expected <!-- file: NAME -->, e.g. <!-- file: plan.toml -->")
            blocks.append(Block(start + 1, language, code, "file", file_name=name))
    return blocks


def run_blocks(path: str | Path) -> int:
    """Execute the blocks of the Markdown file at ``path`` in the current directory.

    Returns 0, or 1 after writing the failing block's line and error to stderr.
    """
    path = Path(path).resolve()
    try:
        blocks = parse_blocks(path.read_text(encoding="utf-8"), str(path))
    except ValueError as exc:
        print(exc, file=sys.stderr)
        return 1
    namespace = {"__name__": "__main__"}
    for block in blocks:
        if block.action == "file":
            target = Path(block.file_name)
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(block.code, encoding="utf-8")
        elif block.action == "python":
            # pad so that tracebacks give the Markdown file's line numbers
            code = compile("\n" * block.line + block.code, str(path), "exec")
            try:
                exec(code, namespace)
            except BaseException:  # noqa: BLE001 - any failure of an example is reported
                print(f"{path.name}:{block.line}: python block failed\n{traceback.format_exc()}", file=sys.stderr)
                return 1
        elif block.action == "bash":
            sys.stdout.flush()
            done = subprocess.run(["bash", "-e", "-c", block.code], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                  text=True)
            sys.stdout.write(done.stdout)
            if done.returncode:
                tail = "\n".join(done.stdout.splitlines()[-40:])
                print(f"{path.name}:{block.line}: bash block exited with status {done.returncode}\n{tail}",
                      file=sys.stderr)
                return 1
    return 0


def run_markdown(path: str | Path, cwd: str | Path, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    """Run :func:`run_blocks` on ``path`` in a fresh Python process working in ``cwd``."""
    env = dict(os.environ)
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env["MPLBACKEND"] = "Agg"
    return subprocess.run([sys.executable, str(Path(__file__).resolve()), "run", str(Path(path).resolve())],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout)


def _markdown_files() -> list[Path]:
    files = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    return [p for p in files if p.is_file()]


MARKDOWN = _markdown_files()


@pytest.mark.long
@pytest.mark.docs
@pytest.mark.parametrize("path", MARKDOWN, ids=[p.name for p in MARKDOWN])
def test_markdown_blocks_run(path, tmp_path):
    done = run_markdown(path, tmp_path)
    if done.returncode:
        pytest.fail(f"{path.relative_to(ROOT)}: {done.stderr.strip()[-6000:]}", pytrace=False)


# ---- the harness itself, on small Markdown files ------------------------------------

def test_parse_runs_python_and_bash_and_skips_other_fences():
    text = "\n".join([
        "# Title",
        "```python",
        "x = 1",
        "```",
        "```bash",
        "echo hi",
        "```",
        "```text",
        "not run",
        "```",
        "```console",
        "$ toolkit --help",
        "```",
        "```toml",
        "a = 1",
        "```",
        "```",
        "no language",
        "```",
    ])
    blocks = parse_blocks(text)
    assert [(b.line, b.language, b.action) for b in blocks] == [
        (2, "python", "python"), (5, "bash", "bash"), (8, "text", "skip"), (11, "console", "skip"),
        (14, "toml", "skip"), (17, "", "skip")]
    assert blocks[0].code == "x = 1\n"


def test_parse_markers():
    text = "\n".join([
        "<!-- norun: 20-minute paper benchmark -->",
        "```bash",
        "python benchmarks/static_ladder.py",
        "```",
        "<!-- file: plans/plan.toml -->",
        "```toml",
        "[lefort]",
        "```",
        "<!-- norun: installs the package -->",
        "",
        "```python",
        "import toolkit",
        "```",
    ])
    norun, written, after_blank = parse_blocks(text)
    assert (norun.action, norun.reason) == ("skip", "20-minute paper benchmark")
    assert (written.action, written.file_name, written.code) == ("file", "plans/plan.toml", "[lefort]\n")
    assert after_blank.action == "python"  # a marker applies only on the line just before the fence


@pytest.mark.parametrize("marker", ["<!-- norun -->", "<!-- norun: -->", "<!-- norun:   -->"])
def test_norun_without_reason_is_an_error(marker):
    with pytest.raises(ValueError, match=r"page.md:2: .*gives no reason"):
        parse_blocks(f"text\n{marker}\n```python\n1/0\n```\n", "page.md")


@pytest.mark.parametrize("language", sorted(ALIASES))
def test_alias_of_a_run_language_is_an_error(language):
    with pytest.raises(ValueError, match=rf"page.md:2: fence ```{language} is not run; write ```{ALIASES[language]}"):
        parse_blocks(f"x\n```{language}\necho 1\n```\n", "page.md")
    norun, = parse_blocks(f"<!-- norun: shown only -->\n```{language}\necho 1\n```\n")
    assert norun.action == "skip"


def test_file_marker_without_name_and_unclosed_fence_are_errors():
    with pytest.raises(ValueError, match="gives no file name"):
        parse_blocks("<!-- file: -->\n```toml\na = 1\n```\n")
    with pytest.raises(ValueError, match=r"page.md:2: .*never closed"):
        parse_blocks("x\n```python\nprint(1)\n", "page.md")


def test_parse_longer_and_indented_fences():
    text = "\n".join([
        "````markdown",
        "```python",
        "shown, not run",
        "```",
        "````",
        "1. a step:",
        "",
        "   ```python",
        "   if True:",
        "       y = 2",
        "   ```",
    ])
    outer, step = parse_blocks(text)
    assert (outer.language, outer.action) == ("markdown", "skip")
    assert "```python" in outer.code
    assert (step.line, step.code) == (8, "if True:\n    y = 2\n")


def test_run_shares_one_namespace_and_directory(tmp_path):
    page = tmp_path / "page.md"
    page.write_text("\n".join([
        "<!-- file: plan.toml -->",
        "```toml",
        "value = 3",
        "```",
        "```python",
        "import tomllib",
        "value = tomllib.load(open('plan.toml', 'rb'))['value']",
        "open('from_python.txt', 'w').write(str(value))",
        "```",
        "```bash",
        "test \"$(cat from_python.txt)\" = 3",
        "command -v python > python_path.txt",
        "```",
        "```python",
        "assert value == 3  # the namespace of the first block",
        "```",
        "<!-- norun: would fail -->",
        "```python",
        "raise SystemExit(1)",
        "```",
    ]), encoding="utf-8")
    work = tmp_path / "work"
    work.mkdir()
    done = run_markdown(page, work, timeout=120)
    assert done.returncode == 0, done.stderr
    assert (work / "plan.toml").read_text() == "value = 3\n"
    assert Path((work / "python_path.txt").read_text().strip()).parent == Path(sys.executable).parent


@pytest.mark.parametrize("block, message", [
    ("```python\nx = 1\ny = 1 / 0\n```", r"page.md:5: python block failed.*page.md\", line 7.*ZeroDivisionError"),
    ("```bash\nfalse\necho unreached\n```", r"page.md:5: bash block exited with status 1"),
])
def test_run_reports_the_failing_block(tmp_path, block, message):
    page = tmp_path / "page.md"
    page.write_text(f"# Page\n\n```python\n```\n{block}\n", encoding="utf-8")
    done = run_markdown(page, tmp_path, timeout=120)
    assert done.returncode == 1
    assert re.search(message, done.stderr, re.S), done.stderr
    assert "unreached" not in done.stdout


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] != "run":
        sys.exit(f"usage: python {sys.argv[0]} run FILE.md (got {sys.argv[1:]})")
    sys.exit(run_blocks(sys.argv[2]))
