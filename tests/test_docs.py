"""The docs say what the code does: every estimator option in the method page with its default and
its ``paper`` preset value, every ``lfrig`` command line shown in README.md and docs/*.md made of
commands and flags that exist, every project file they name present, the user guide's boards the
demo's own, and no words of a development diary.

Commands are checked against the parser ``lfrig`` itself builds (``rig.main.build_parser``); every
line of the pages' shell blocks is also run, by ``tests/test_docs_run.py``. See ``docs/entropy-method.md`` for the option tables' form (``| `name` | `default` | `paper` |
meaning |``).
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import re
from pathlib import Path

import pytest

from recon.entropy import EntropyOptions, make_options
from rig.demo import INTRINSICS_BOARD, STAGE_BOARD
from rig.main import build_parser

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
METHOD_PAGE = ROOT / "docs" / "entropy-method.md"
#: A row of an option table: | `name` | `default` | `paper value` or empty | meaning |
OPTION_ROW = re.compile(r"^\| `(\w+)` \| `([^`]*)` \| (?:`([^`]*)`)? *\|")


def option_rows(text: str) -> dict[str, tuple[object, object | None]]:
    """``name -> (default, paper value or None)`` from the method page's option tables."""
    rows: dict[str, tuple[object, object | None]] = {}
    for line in text.splitlines():
        m = OPTION_ROW.match(line)
        if m:
            assert m.group(1) not in rows, f"{m.group(1)} is listed twice"
            paper = None if m.group(3) is None else ast.literal_eval(m.group(3))
            rows[m.group(1)] = (ast.literal_eval(m.group(2)), paper)
    return rows


def test_method_page_lists_every_option_with_its_default_and_paper_value():
    rows = option_rows(METHOD_PAGE.read_text(encoding="utf-8"))
    fields = {f.name: f.default for f in dataclasses.fields(EntropyOptions)}
    assert sorted(set(fields) - set(rows)) == [], "options missing from docs/entropy-method.md"
    assert sorted(set(rows) - set(fields)) == [], "the method page lists options that do not exist"
    paper_preset = make_options(preset="paper")
    for name, (default, paper) in rows.items():
        assert default == fields[name], f"{name}: the page says {default!r}, the code {fields[name]!r}"
        expected = getattr(paper_preset, name)
        assert (default if paper is None else paper) == expected, \
            f"{name}: the page's paper value is {paper!r}, the preset's {expected!r}"
        assert paper is None or paper != default, f"{name}: a paper value equal to the default"


def test_method_page_is_a_reference_of_at_most_350_lines():
    assert len(METHOD_PAGE.read_text(encoding="utf-8").splitlines()) <= 350


def command_lines(text: str) -> list[tuple[int, str]]:
    """``(line number, arguments after 'lfrig')`` of every ``lfrig`` command in the fenced code
    blocks (continued lines joined, comments dropped) and in inline code spans."""
    found = []
    lines = text.splitlines()
    fenced = False
    for i, line in enumerate(lines):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            m = re.search(r"(?:^|[\s/])lfrig\s+(.*)", line)
            if m:
                command, j = m.group(1), i
                while command.rstrip().endswith("\\") and j + 1 < len(lines):
                    j += 1
                    command = command.rstrip()[:-1] + " " + lines[j].strip()
                found.append((i + 1, command.split(" #")[0]))
        else:
            found += [(i + 1, m.group(1)) for m in re.finditer(r"`(?:\.venv/bin/)?lfrig\s+([^`]*)`", line)]
    return found


@functools.cache
def lfrig_parser() -> argparse.ArgumentParser:
    return build_parser()


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def resolve(parser: argparse.ArgumentParser, words: list[str]) -> tuple[argparse.ArgumentParser, list[str]]:
    """The (sub)parser the leading words name, and the words it was named by."""
    path = []
    for word in words:
        sub = subcommands(parser)
        if word not in sub:
            break
        parser = sub[word]
        path.append(word)
    return parser, path


def documented_commands():
    for page in DOCS:
        for number, command in command_lines(page.read_text(encoding="utf-8")):
            yield pytest.param(command, id=f"{page.name}:{number}")


@pytest.mark.parametrize("command", list(documented_commands()))
def test_documented_command_uses_commands_and_flags_that_exist(command):
    words = command.split()
    parser, path = resolve(lfrig_parser(), words)
    if not path:  # `lfrig --help` or a placeholder such as `lfrig COMMAND`
        assert not words or words[0].startswith("-") or words[0].isupper(), f"no command {words[0]!r}"
        parser = lfrig_parser()
    elif subcommands(parser) and len(words) > len(path) and not words[len(path)].startswith("-"):
        pytest.fail(f"lfrig {' '.join(path)} has no action {words[len(path)]!r}")
    known = set(parser._option_string_actions)
    flags = [w.split("=")[0] for w in words if re.fullmatch(r"--[a-z][a-z0-9-]*(=.*)?", w)]
    assert [f for f in flags if f not in known] == [], f"lfrig {' '.join(path)} has no such flag"


def board_flags(command: str) -> tuple[int, int, float]:
    cols, rows = re.search(r"--board (\d+)x(\d+)", command).groups()
    return int(cols), int(rows), float(re.search(r"--square-mm ([\d.]+)", command).group(1))


def test_user_guide_calibrates_on_the_demos_own_boards():
    commands = [c for _, c in command_lines((ROOT / "docs" / "user-guide.md").read_text(encoding="utf-8"))]
    intrinsics = [board_flags(c) for c in commands if c.startswith("calibrate intrinsics")]
    stage = [board_flags(c) for c in commands if c.startswith("calibrate stage")]
    assert intrinsics and set(intrinsics) == {INTRINSICS_BOARD}
    assert stage and set(stage) == {STAGE_BOARD}


#: How the code was made is not what it does: words of a development diary (a lab session,
#: ``session.log``, ``rig/session.py``, a branch of the exception tree and lead screws are fine).
DIARY = re.compile(r"\bsession \d|\b(this|that|the other|a feature) branch\b|\bthe lead\b|\blead's\b"
                   r"|\bon main\b|\bmain's\b|\bmerg(e|ed|ing) (of )?(main|the branch)\b|\bthis session\b",
                   re.IGNORECASE)


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_docs_describe_the_product_not_how_it_was_made(page):
    hits = [f"{page.name}:{n}: {line.strip()}" for n, line in
            enumerate(page.read_text(encoding="utf-8").splitlines(), 1) if DIARY.search(line)]
    assert hits == []


#: A file of the project named in the docs, in backticks: `recon/...`, `tests/...`, `bench/...` ...
PROJECT_PATH = re.compile(r"`((?:recon|rig|calib|tests|bench|docs|fixtures)/[A-Za-z0-9_./-]*)`")


@pytest.mark.parametrize("page", DOCS, ids=lambda p: p.name)
def test_files_the_docs_name_exist(page):
    named = set(PROJECT_PATH.findall(page.read_text(encoding="utf-8")))
    assert sorted(p for p in named if not (ROOT / p).exists()) == []
