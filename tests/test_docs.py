"""The repository's citations of the model's reference resolve inside the repository.

Every ``docs/model.md §…`` (or ``docs/model.md#anchor``) citation in the code, tests, notes,
README and notebooks names a section (or a trap of §6) that exists in ``docs/model.md``, and no
file points at the former out-of-repository specification. Plain text checks: MkDocs is not
needed (``mkdocs build --strict`` in ``.ci/run`` checks the site's own links).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MODEL = ROOT / "docs" / "model.md"

# Spelled in pieces so that this file does not match itself.
FORBIDDEN = ("MODEL" + ".md", "../shared" + "/spec", "shared" + "/spec/")

# Folders that are not the repository's own text (environments, build output, caches).
_SKIP_DIRS = {".git", "site", "build", "dist", "__pycache__", ".hypothesis", "example-out"}
_MAX_BYTES = 5_000_000

_HEADING = re.compile(r"^(#{1,6})\s+(?:(\d+(?:\.\d+)*)\.?\s+)?(.*?)\s*(?:\{#([\w.-]+)\})?\s*$")
_CITE = re.compile(r"docs/model\.md")
_REF = re.compile(
    r"§\s?(\d+(?:\.\d+)*)(?:\s*[-–]\s*(\d+(?:\.\d+)*))?(?:\s+traps?\s+(\d+)(?:\s*[-–]\s*(\d+))?)?"
)
_NEXT_REF = re.compile(r"(?:,\s*|\s+and\s+)(?=§)")


def _skipped(rel: Path) -> bool:
    return any(
        part in _SKIP_DIRS
        or part.startswith(".venv")
        or part.endswith(".egg-info")
        or part.endswith("_cache")
        or part == ".ipynb_checkpoints"
        for part in rel.parts[:-1]
    )


def _repository_files() -> list[Path]:
    """Tracked and untracked-but-not-ignored files (git), else a walk with the usual skips."""
    git = shutil.which("git")
    if git and (ROOT / ".git").exists():
        out = subprocess.run(
            [git, "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            cwd=ROOT,
            capture_output=True,
            check=True,
        ).stdout
        rels = {Path(r) for r in out.decode().split("\0") if r}
    else:
        rels = {p.relative_to(ROOT) for p in ROOT.rglob("*")}
    return sorted(
        ROOT / r for r in rels if not _skipped(r) and (ROOT / r).is_file() and r.parts[0] != "site"
    )


def _text(path: Path) -> str | None:
    """The file's text (a notebook's cell sources), or None for binary and very large files."""
    if path.stat().st_size > _MAX_BYTES:
        return None
    data = path.read_bytes()
    if b"\0" in data[:8192]:
        return None
    text = data.decode("utf-8", errors="replace")
    if path.suffix == ".ipynb":
        try:
            cells = json.loads(text).get("cells", [])
        except ValueError:
            return text
        sources = ("".join(c.get("source", "")) for c in cells)
        outputs = (json.dumps(c.get("outputs", []), ensure_ascii=False) for c in cells)
        return "\n".join([*sources, *outputs])
    return text


def _model_sections():
    """Section numbers, anchors and the numbered traps of §6 in docs/model.md."""
    numbers, anchors, traps, unanchored = set(), [], set(), []
    section, fenced = None, False
    for line in MODEL.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        m = _HEADING.match(line)
        if m and line.startswith("#"):
            number, anchor = m.group(2), m.group(4)
            section = number
            if number:
                numbers.add(number)
                if not anchor:
                    unanchored.append(line)
            if anchor:
                anchors.append(anchor)
            continue
        t = re.match(r"^(\d+)\.\s", line)
        if t and section == "6":
            traps.add(int(t.group(1)))
    return numbers, anchors, traps, unanchored


NUMBERS, ANCHORS, TRAPS, UNANCHORED = _model_sections()
FILES = _repository_files()


def _check_refs(text: str, start: int, where: str, problems: list[str]) -> None:
    """Parse ``§a[-b][ traps x[-y]][, §…]`` at ``text[start:]`` and check each part."""
    pos = start
    while True:
        m = _REF.match(text, pos)
        if not m:
            return
        first, last, trap_lo, trap_hi = m.groups()
        for number in (first, last):
            if number is not None and number not in NUMBERS:
                problems.append(f"{where}: §{number} is not a section of docs/model.md")
        if trap_lo is not None:
            if first != "6":
                problems.append(f"{where}: traps are numbered in §6, not §{first}")
            for trap in (trap_lo, trap_hi):
                if trap is not None and int(trap) not in TRAPS:
                    problems.append(f"{where}: §6 has no trap {trap}")
        pos = m.end()
        sep = _NEXT_REF.match(text, pos)
        if not sep:
            return
        pos = sep.end()


def test_model_page_structure():
    """Numbered sections, each with an explicit, unique anchor; §6 lists its traps."""
    assert {"1", "2", "3", "3.1", "3.11", "4", "5", "6", "7", "8"} <= NUMBERS
    assert not UNANCHORED, f"numbered headings without an explicit {{#anchor}}: {UNANCHORED}"
    duplicates = sorted({a for a in ANCHORS if ANCHORS.count(a) > 1})
    assert not duplicates, f"anchors used twice in docs/model.md: {duplicates}"
    assert set(range(1, 9)) <= TRAPS


def test_model_page_internal_references():
    """The page's own ``§N`` references name its sections."""
    text = MODEL.read_text(encoding="utf-8")
    problems: list[str] = []
    for m in re.finditer("§", text):
        line = text.count("\n", 0, m.start()) + 1
        _check_refs(text, m.start(), f"docs/model.md:{line}", problems)
    assert not problems, "\n".join(problems)


def test_citations_resolve():
    """Every ``docs/model.md §…`` / ``docs/model.md#…`` in the repository names a real section.

    In Python files a mention must carry a section; Markdown may also link to the whole page.
    """
    problems: list[str] = []
    n_citations = 0
    for path in FILES:
        text = None if path == Path(__file__).resolve() else _text(path)
        if text is None or "docs/model.md" not in text:
            continue
        rel = path.relative_to(ROOT).as_posix()
        for m in _CITE.finditer(text):
            where = f"{rel}:{text.count(chr(10), 0, m.start()) + 1}"
            pos = m.end()
            while pos < len(text) and text[pos] in "`'\"":
                pos += 1
            if text.startswith("#", pos):
                anchor = re.match(r"#([\w.-]+)", text[pos:])
                if not anchor or anchor.group(1) not in ANCHORS:
                    problems.append(f"{where}: no anchor {text[pos : pos + 30]!r} in docs/model.md")
                n_citations += 1
                continue
            gap = re.match(r"\s*(?:'s\s+)?", text[pos:]).end()
            if text.startswith("§", pos + gap):
                n_citations += 1
                _check_refs(text, pos + gap, where, problems)
            elif path.suffix == ".py":
                problems.append(f"{where}: a citation of docs/model.md without a section")
    assert not problems, "\n".join(problems)
    assert n_citations >= 50  # the code does cite the page (a vanished form would pass vacuously)


@pytest.mark.parametrize("needle", FORBIDDEN)
def test_no_links_out_of_the_repository(needle):
    """Nothing refers to the out-of-repository specification any more."""
    hits = []
    for path in FILES:
        text = _text(path)
        if text is not None and needle in text:
            line = text[: text.index(needle)].count("\n") + 1
            hits.append(f"{path.relative_to(ROOT).as_posix()}:{line}")
    assert not hits, f"{needle!r} still referred to in: {hits}"
