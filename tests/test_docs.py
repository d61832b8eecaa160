"""The README and docs/ as a user reads them: every command they show runs (its --help), every
flag they give it exists, and the pages stay a reference of readable size."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
README_MAX_BYTES = 12_000
PAGE_MAX_BYTES = 40_000


def code_lines(page: Path) -> list[str]:
    """The lines of a page's code blocks (indented by four spaces or fenced), with a trailing
    backslash joining a line to the next."""
    lines, fenced, pending = [], False, ""
    for raw in page.read_text().splitlines():
        if raw.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not (fenced or raw.startswith("    ")):
            pending = ""
            continue
        text = pending + raw.strip()
        if text.endswith("\\"):
            pending = text[:-1] + " "
            continue
        pending = ""
        lines.append(text)
    return lines


def python_commands(page: Path) -> list[tuple[str, list[str]]]:
    """(program, flags) of each `python ...` command of a page's code: program is a script path
    or `-m module` of this project; flags are the `--names` given to it (up to a bare `--`)."""
    out = []
    for line in code_lines(page):
        try:
            words = shlex.split(line, comments=True)
        except ValueError:  # an unbalanced quote in an example's prose
            continue
        if not words or words[0] not in ("python", "python3"):
            continue
        if words[1:2] == ["-m"]:
            if len(words) < 3 or not words[2].startswith("legged_casters"):
                continue
            program, rest = f"-m {words[2]}", words[3:]
        elif len(words) > 1 and words[1].endswith(".py"):
            program, rest = words[1], words[2:]
        else:
            continue
        if "--" in rest:
            rest = rest[: rest.index("--")]
        words = [w.strip("[]") for w in rest]  # a usage line's [--optional] flags too
        flags = [w.split("=", 1)[0] for w in words if w.startswith("--")]
        out.append((program, flags))
    return out


@cache
def help_text(program: str) -> str:
    argv = [sys.executable, *program.split()] + ["--help"]
    proc = subprocess.run(argv, cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, f"{program} --help exited {proc.returncode}: {proc.stderr[-1500:]}"
    return proc.stdout


COMMANDS = sorted({(page.name, program, tuple(flags)) for page in PAGES for program, flags in python_commands(page)})


def test_the_pages_show_commands():
    programs = {program for _, program, _ in COMMANDS}
    for expected in ("play.py", "export.py", "scripts/evaluate.py", "-m legged_casters.deploy.bridge"):
        assert expected in programs, sorted(programs)
    assert ("README.md", "play.py", ()) in COMMANDS  # the quick start's bare `python play.py`


@pytest.mark.parametrize("program", sorted({program for _, program, _ in COMMANDS}))
def test_every_command_a_page_shows_runs_and_knows_its_flags(program):
    """`<program> --help` runs, and every flag any page gives the program is in that help:
    a renamed or removed flag breaks this test, not a user's first try."""
    if not program.startswith("-m") and not (REPO / program).is_file():
        pytest.fail(f"the docs run {program}, which is not in the repository")
    text = help_text(program)
    for page, prog, flags in COMMANDS:
        if prog != program:
            continue
        missing = [f for f in flags if not re.search(rf"(?<![\w-]){re.escape(f)}(?![\w-])", text)]
        assert not missing, f"{page}: `{program}` is given {missing}, which its --help does not list"


def test_setup_sh_has_the_steps_the_readme_names():
    readme = (REPO / "README.md").read_text()
    steps = set(re.findall(r"\./setup\.sh (\w+)", readme))
    assert {"install", "train", "test"} <= steps
    setup = (REPO / "setup.sh").read_text()
    for step in steps:
        assert re.search(rf"^\s*{step}\)", setup, re.M), f"README names ./setup.sh {step}, which setup.sh lacks"


def test_pages_are_a_reference_not_a_notebook():
    """Small pages, and no development narrative: issue numbers, waves, sessions or run numbers."""
    assert (REPO / "README.md").stat().st_size <= README_MAX_BYTES
    narrative = re.compile(r"\b[Ii]ssue \d+|\bwaves?\b|\bsessions?\b(?! of)|\bruns? \d{2,3}\b")
    for page in PAGES:
        text = page.read_text()
        assert page.stat().st_size <= PAGE_MAX_BYTES, f"{page.name}: {page.stat().st_size} bytes"
        found = [m.group(0) for m in narrative.finditer(text) if "zenoh" not in text[max(0, m.start() - 40) : m.end()]]
        assert not found, f"{page.name}: {found[:5]}"
