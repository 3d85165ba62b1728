"""Every section of docs/ALGORITHM.md that the source tree cites exists: code, tests, benches and
the READMEs cite the method document as ``docs/ALGORITHM.md §N`` (``§4.2``, ``§I.5``, ...), and a
renumbered or deleted section must not leave a citation pointing at nothing.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "ALGORITHM.md"
SIGN = "\u00a7"  # the section sign, spelled out so this file cites nothing itself

# A section id: numbers ("3", "4.2") or a capital letter with optional numbers ("S", "I.5").
SECTION_ID = r"(?:[0-9]+(?:\.[0-9]+)*|[A-Z](?:\.[0-9]+)*)(?![A-Za-z0-9])"
# A heading of the document: "## 4. Solving ...", "### 4.2 Back-propagation", "## S. The ...".
HEADING = re.compile(rf"^#{{2,6}}\s+({SECTION_ID})\.?\s")
# Any citation of a section: the sign followed by an id (bare, as in "§4.1, §4.2", or after the
# document's name). A sign after another document's name ("FORMATS.md §2") is not ours.
CITATION = re.compile(rf"(?:(\S+\.md)\]?(?:\([^)]*\))?\s+)?{SIGN}\s?({SECTION_ID})")

# Where the method is cited: the code, the tests, the benches, and the Markdown documents.
SCANNED_DIRS = ("python", "rust/src", "tests", "benches", "docs")
SCANNED_FILES = ("README.md",)
SUFFIXES = {".py", ".pyi", ".rs", ".md", ".js", ".html", ".css", ".toml", ".txt"}


def doc_sections(text: str) -> set[str]:
    """The section ids of the document's headings."""
    out = set()
    for line in text.splitlines():
        m = HEADING.match(line)
        if m:
            out.add(m.group(1))
    return out


def citations(text: str) -> list[tuple[int, str]]:
    """(line, section id) of every citation of docs/ALGORITHM.md in ``text``."""
    out = []
    for number, line in enumerate(text.splitlines(), 1):
        for m in CITATION.finditer(line):
            named = m.group(1)
            if named is not None and not named.rstrip("]").endswith("ALGORITHM.md"):
                continue
            out.append((number, m.group(2)))
    return out


def scanned_files() -> list[Path]:
    files = [ROOT / name for name in SCANNED_FILES]
    for folder in SCANNED_DIRS:
        base = ROOT / folder
        files += [
            p
            for p in base.rglob("*")
            if p.is_file() and p.suffix in SUFFIXES and "__pycache__" not in p.parts
        ]
    here = Path(__file__).resolve()
    return sorted(p for p in files if p.resolve() != here)


def test_the_document_has_numbered_sections() -> None:
    sections = doc_sections(DOC.read_text(encoding="utf-8"))
    # The method's parts, the solver and issue 11's additions, each findable by its number.
    for expected in ("1", "2", "3", "3.3", "4", "4.1", "4.2", "4.3", "5", "6", "S", "S.4", "I.5"):
        assert expected in sections, f"docs/ALGORITHM.md has no section {expected}"


def test_every_cited_section_exists() -> None:
    sections = doc_sections(DOC.read_text(encoding="utf-8"))
    missing = []
    seen = 0
    for path in scanned_files():
        text = path.read_text(encoding="utf-8", errors="replace")
        for line, section in citations(text):
            seen += 1
            if section not in sections:
                missing.append(f"{path.relative_to(ROOT)}:{line}: {SIGN}{section}")
    # The tree cites the document in dozens of places; finding none means the scan is broken.
    assert seen > 50, f"only {seen} citations found; is the scan looking in the right places?"
    assert not missing, (
        "citations of sections that docs/ALGORITHM.md does not have (its sections: "
        f"{', '.join(sorted(sections))}):\n" + "\n".join(missing)
    )


def test_citations_name_the_document_by_its_path() -> None:
    """Written one way everywhere: ``docs/ALGORITHM.md §N``. A file that cites a bare section
    must say which document it means; the design card's ``ALGORITHM.md`` (outside the
    repository) is not what the code cites."""
    bad = []
    for path in scanned_files():
        if path == DOC:
            continue
        text = path.read_text(encoding="utf-8", errors="replace")
        rel = path.relative_to(ROOT)
        for number, line in enumerate(text.splitlines(), 1):
            for m in re.finditer(r"(\S*)ALGORITHM(\.md)?", line):
                if not (m.group(1).endswith("docs/") and m.group(2)):
                    bad.append(f"{rel}:{number}: {line.strip()}")
        if citations(text) and "docs/ALGORITHM.md" not in text:
            bad.append(f"{rel}: cites {SIGN} sections but never names docs/ALGORITHM.md")
    assert not bad, "write docs/ALGORITHM.md:\n" + "\n".join(bad)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (f"see docs/ALGORITHM.md {SIGN}4.2.", [(1, "4.2")]),
        (f"(docs/ALGORITHM.md {SIGN}4.1, {SIGN}4.2)", [(1, "4.1"), (1, "4.2")]),
        (f"[docs/ALGORITHM.md](docs/ALGORITHM.md) {SIGN}S", [(1, "S")]),
        (f"rules of {SIGN}I.5; and {SIGN}I.", [(1, "I.5"), (1, "I")]),
        (f"FORMATS.md {SIGN}2 is another document", []),
        ("no citation here", []),
    ],
)
def test_citations_are_parsed(text: str, expected: list[tuple[int, str]]) -> None:
    assert citations(text) == expected


def test_a_missing_section_is_reported() -> None:
    sections = doc_sections("# title\n## 1. One\n### 1.1 Sub\n## S. Solver\n")
    assert sections == {"1", "1.1", "S"}
    cited = [s for _, s in citations(f"docs/ALGORITHM.md {SIGN}1.2 and {SIGN}S")]
    assert [s for s in cited if s not in sections] == ["1.2"]
