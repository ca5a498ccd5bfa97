"""The user guide stays honest: README.md and docs/**/*.md.

- No line reads like a development diary ("stop 12", "this session", "the
  code before", "(issue 15)") or names a planning file that is not in the
  repository: the guide describes the product as it is.
- Every repository file the guide names (a markdown link, or a backticked
  ``dir/file.ext`` path) exists, and every ``python -m dtpf....`` module it
  names can be found.
- README.md starts with a "Quick start" of exactly two commands and stays
  at most 300 lines.

Each checker is also run on a small sample it must flag, so a checker that
matches nothing fails here rather than passing everything.
"""
from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = sorted((ROOT / "docs").rglob("*.md"))
GUIDE = [README, *DOCS]

#: How a development diary reads; none of it belongs in a user guide.
DIARY = [
    r"\bstop \d+\b",
    r"\b(this|that|each|the previous|a later|an earlier) stop\b",
    r"\b(this|that|a later|an earlier|the previous|later|earlier) session\b",
    r"\bthe code before\b",
    r"\bran here\b",
    r"\(issue \d+\)",
    r"\bissue \d+\b",
    r"\bissues? #\d+\b",
    r"\bwas tried and not kept\b",
    r"DESIGN\.md|ECOSYSTEM\.md|PERF-ANCHORS\.md|STYLE\.md",
]
_DIARY = [re.compile(pattern, re.IGNORECASE) for pattern in DIARY]

#: Extensions that make a backticked ``dir/name.ext`` a repository file.
_EXTENSIONS = ("md", "py", "json", "json5", "csv", "png", "toml", "txt", "npz", "npy", "cfg", "yml", "yaml", "sh")
_PATH = re.compile(r"(?<![\w/.-])((?:[\w.-]+/)+[\w.-]+\.(?:" + "|".join(_EXTENSIONS) + r"))(?![\w/])")
_LINK = re.compile(r"\]\(([^)\s]+)\)")
_CODE = re.compile(r"`([^`\n]+)`")
_FENCE = re.compile(r"^\s*```")
_MODULE = re.compile(r"python3? -m ([A-Za-z_][\w.]*)")

#: Paths the guide names that are not repository files, on purpose: where a
#: command writes, and the placeholder of a user's own file. Keep this short.
NOT_IN_REPOSITORY = {
    "path/to/file.py",  # the form of --model REF
    "my_models/tracking.py",  # a user's package, in the entry-point example
}
#: Folders a command writes into (dtpf launch -o runs/..., dtpf secure init deploy).
OUTPUT_FOLDERS = ("runs/", "deploy/", "machine-a/", "machine-b/", "/tmp/")
#: Modules of other projects the guide runs with python -m.
OTHER_MODULES = {"pip", "pytest", "venv"}


def diary_lines(text: str) -> list[tuple[int, str, str]]:
    """(line number, pattern, line) for every line that reads like a diary."""
    found = []
    for number, line in enumerate(text.splitlines(), 1):
        for pattern in _DIARY:
            if pattern.search(line):
                found.append((number, pattern.pattern, line.strip()))
    return found


def _outside_fences(text: str) -> list[tuple[int, str]]:
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), 1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, line))
    return lines


def _placeholder(path: str) -> bool:
    return any(mark in path for mark in ("<", ">", "*", "...", "{", "}")) or path.startswith(OUTPUT_FOLDERS)


def named_paths(text: str) -> list[tuple[int, str, str]]:
    """(line number, kind, path) for each repository path a page names: the
    targets of its markdown links and the ``dir/file.ext`` paths in its inline
    code (fenced blocks are commands and their output, not references)."""
    found = []
    for number, line in _outside_fences(text):
        for target in _LINK.findall(line):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue
            target = target.split("#", 1)[0]
            if target and not _placeholder(target):
                found.append((number, "link", target))
        for code in _CODE.findall(line):
            for path in _PATH.findall(code):
                if not _placeholder(path) and path not in NOT_IN_REPOSITORY:
                    found.append((number, "path", path))
    return found


def missing_paths(text: str, page: Path) -> list[tuple[int, str, str]]:
    """The named paths that do not exist. A link resolves against the page's
    folder, as a markdown viewer resolves it; a backticked path against the
    repository root or the page's folder."""
    missing = []
    for number, kind, path in named_paths(text):
        bases = [page.parent] if kind == "link" else [ROOT, page.parent]
        if not any((base / path).exists() for base in bases):
            missing.append((number, kind, path))
    return missing


def missing_modules(text: str) -> list[tuple[int, str]]:
    """``python -m X`` with X neither a dtpf module that exists nor a known tool."""
    missing = []
    for number, line in enumerate(text.splitlines(), 1):
        for module in _MODULE.findall(line):
            module = module.rstrip(".")
            if module in OTHER_MODULES:
                continue
            if not module.startswith("dtpf.") or importlib.util.find_spec(module) is None:
                missing.append((number, module))
    return missing


def quick_start_commands(text: str) -> list[str] | None:
    """The commands of the first code block after the "Quick start" heading."""
    lines = text.splitlines()
    heading = next((i for i, line in enumerate(lines) if re.match(r"#+\s*Quick start\s*$", line)), None)
    if heading is None:
        return None
    start = next((i for i in range(heading + 1, len(lines)) if _FENCE.match(lines[i])), None)
    if start is None:
        return None
    end = next((i for i in range(start + 1, len(lines)) if _FENCE.match(lines[i])), len(lines))
    return [line.strip() for line in lines[start + 1:end] if line.strip() and not line.strip().startswith("#")]


def _name(page: Path) -> str:
    return str(page.relative_to(ROOT))


# The checkers flag what they are for.

def test_the_diary_checker_flags_a_diary_line_and_passes_a_plain_one():
    for bad in ("Stop 25. This stop's machine is slower again.", "as a later session found",
                "(issue 15)", "see PERF-" + "ANCHORS.md section 4", "the same runs of the code before gave 686",
                "The same commands with 127.0.0.1 ran here"):
        assert diary_lines(bad), bad
    assert not diary_lines("Each step the entity publishes its particle set; the session closes at exit.")


def test_the_path_checker_flags_a_missing_file_and_passes_present_ones():
    page = ROOT / "docs" / "page.md"
    text = ("See [the design](DESIGN-notes.md) and `messages/bus.py`; the model is\n"
            "`docs/examples/range_bearing.py` and [its data](examples/range_bearing.csv).\n"
            "```\nnot/checked/in_a_fence.py\n```\n"
            "Written by a command: `runs/demo.mcap`; a placeholder: `dtpf/<twin>/x.json`.\n")
    assert [path for _, _, path in missing_paths(text, page)] == ["DESIGN-notes.md", "messages/bus.py"]
    assert sorted(path for _, _, path in named_paths(text)) == [
        "DESIGN-notes.md", "docs/examples/range_bearing.py", "examples/range_bearing.csv", "messages/bus.py"]


def test_the_module_checker_flags_a_module_that_moved():
    assert missing_modules("python -m scripts.bench.fleet --cases 1e3:100") == [(1, "scripts.bench.fleet")]
    assert missing_modules("python -m dtpf.scripts.bench.fleet and python3 -m pytest") == []


def test_the_quick_start_reader_counts_commands():
    text = "# x\n\n## Quick start\n\n```sh\n# a comment\none\n\ntwo\n```\n\n```sh\nthree\n```\n"
    assert quick_start_commands(text) == ["one", "two"]
    assert quick_start_commands("# x\n```sh\none\n```\n") is None


# The guide itself.

def test_the_guide_has_pages():
    assert README.is_file()
    assert len(DOCS) >= 5, DOCS


@pytest.mark.parametrize("page", GUIDE, ids=_name)
def test_no_page_reads_like_a_development_diary(page: Path):
    found = diary_lines(page.read_text())
    assert not found, "\n".join(f"{_name(page)}:{n}: /{p}/: {line}" for n, p, line in found)


@pytest.mark.parametrize("page", GUIDE, ids=_name)
def test_every_file_a_page_names_exists(page: Path):
    found = missing_paths(page.read_text(), page)
    assert not found, "\n".join(f"{_name(page)}:{n}: {kind} {path} does not exist" for n, kind, path in found)


@pytest.mark.parametrize("page", GUIDE, ids=_name)
def test_every_module_a_page_runs_exists(page: Path):
    found = missing_modules(page.read_text())
    assert not found, "\n".join(f"{_name(page)}:{n}: python -m {module}: no such module" for n, module in found)


def test_the_readme_starts_with_two_commands_and_stays_short():
    text = README.read_text()
    commands = quick_start_commands(text)
    assert commands is not None, "README.md has no 'Quick start' heading followed by a code block"
    assert len(commands) == 2, commands
    assert len(text.splitlines()) <= 300, len(text.splitlines())
