"""The README and the docs name only options that the command they show has: every ``toolkit
...`` command line in a code block or code span, and every row of a table whose first cell names a
command, is checked against that command's parser."""

import argparse
import re
from pathlib import Path

import pytest

from toolkit.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
COMMAND = re.compile(r"toolkit ((?:static|impact) [a-z]+|demo|phantom|ct|mesh)\b(.*)")
OPTION = re.compile(r"(?<![\w-])--[a-z][a-z0-9-]*")
#: options every command takes
COMMON = {"--help", "--version", "--threads", "--verbose"}


def _options() -> dict[tuple[str, ...], set[str]]:
    """Command path (``("static", "predict")``) -> its option strings."""
    out = {}

    def walk(parser, path):
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                for name, sub in action.choices.items():
                    out[path + (name,)] = set(sub._option_string_actions)
                    walk(sub, path + (name,))

    walk(build_parser(), ())
    return out


def _uses(text: str, known) -> list[tuple[tuple[str, ...], set[str]]]:
    """``(command, options)`` of each ``toolkit ...`` command line in ``text``."""
    found = []
    for chunk in re.split(r"(?=toolkit )", text):
        m = COMMAND.match(chunk)
        if m and tuple(m.group(1).split()) in known:
            found.append((tuple(m.group(1).split()), set(OPTION.findall(m.group(2)))))
    return found


def unknown_options(text: str, known) -> list[str]:
    """``"line N: toolkit CMD: --option"`` for every option ``text`` (markdown) gives a command
    that the command does not take."""
    bad, block, pending = [], False, ""
    for number, line in enumerate(text.splitlines(), start=1):
        if line.lstrip().startswith("```"):
            block, pending = not block, ""
            continue
        if block:  # a command line may go on over lines ending with a backslash
            pending += line.rstrip("\\") + " "
            if line.endswith("\\"):
                continue
            texts, pending = [pending], ""
        else:
            cells = line.split("|")
            first = _uses(" ".join(re.findall(r"`([^`]+)`", cells[1])), known) if line.startswith("|") and \
                len(cells) > 2 else []
            if first:  # a table row about one command: every option in the row is that command's
                command = first[0][0]
                bad += [f"line {number}: toolkit {' '.join(command)}: {o}"
                        for o in sorted(set(OPTION.findall(line)) - known[command] - COMMON)]
                continue
            texts = re.findall(r"`([^`]+)`", line)
        for t in texts:
            for command, options in _uses(t, known):
                bad += [f"line {number}: toolkit {' '.join(command)}: {o}"
                        for o in sorted(options - known[command] - COMMON)]
    return bad


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.name)
def test_the_docs_name_only_options_their_commands_take(path):
    assert unknown_options(path.read_text(), _options()) == []


def test_the_check_finds_a_wrong_option_in_a_span_a_block_and_a_table():
    known = _options()
    text = ("Run `toolkit static predict --model m --answerer fe --out o`.\n"
            "```bash\ntoolkit impact simulate --velocity 30 \\\n  --no-image --out x\n```\n"
            "| `toolkit mesh` | meshes (`--size`, `--resolution`) | face.vtu |\n"
            "`toolkit static simulate --mesh f.vtu` reads what `toolkit mesh --no-preview` writes.\n")
    assert unknown_options(text, known) == ["line 1: toolkit static predict: --answerer",
                                            "line 4: toolkit impact simulate: --no-image",
                                            "line 6: toolkit mesh: --resolution"]


def remedies(root: Path, known) -> tuple[int, list[str]]:
    """``(count, problems)`` of the command lines the library's messages and docstrings quote
    (```toolkit ...``` in backticks): a command that does not exist, or an option it does not take."""
    count, bad = 0, []
    for source in sorted(root.rglob("*.py")):
        for quoted in re.findall(r"`(toolkit [^`]+)`", source.read_text()):
            uses = _uses(quoted, known)
            if not uses and re.match(r"toolkit (static|impact) [a-z]", quoted):  # not `toolkit static ...`
                bad.append(f"{source.name}: `{quoted}` names no command")
            for command, options in uses:
                count += 1
                bad += [f"{source.name}: `{quoted}`: {o}" for o in sorted(options - known[command] - COMMON)]
    return count, bad


def test_every_command_line_a_message_quotes_parses():
    """A remedy such as "make one with `toolkit static calibrate --model M --data DB.h5`" names a
    command and options that exist."""
    import toolkit

    count, bad = remedies(Path(toolkit.__file__).parent, _options())
    assert count >= 50 and bad == []


def test_the_remedy_check_finds_a_wrong_option_and_command(tmp_path):
    (tmp_path / "m.py").write_text('raise ValueError("rerun `toolkit static simulate --answerer fe` or '
                                   '`toolkit static fly --out o`")\n')
    assert remedies(tmp_path, _options()) == (1, ["m.py: `toolkit static simulate --answerer fe`: --answerer",
                                                  "m.py: `toolkit static fly --out o` names no command"])
