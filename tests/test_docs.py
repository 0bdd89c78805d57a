"""The README stays a user's document, and every link in it and in docs/ leads somewhere."""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def doc_files() -> list[Path]:
    return [REPO / "README.md", REPO / "tools" / "README.md",
            *sorted(p for p in (REPO / "docs").rglob("*.md") if "archive" not in p.parts)]


def anchors(text: str) -> set[str]:
    """GitHub's anchors of a markdown file's headings."""
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#+ (.+)$", text, re.MULTILINE)}


def test_every_relative_link_in_the_readme_and_docs_points_to_an_existing_file():
    broken = []
    for doc in doc_files():
        text = doc.read_text()
        for target in LINK.findall(text):
            if re.match(r"[a-z]+://", target):
                continue
            path, _, anchor = target.partition("#")
            dest = (doc.parent / path).resolve() if path else doc
            if not dest.exists():
                broken.append(f"{doc.relative_to(REPO)}: {target}")
            elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
                broken.append(f"{doc.relative_to(REPO)}: {target} (no such heading)")
    assert not broken, broken


def test_the_readme_is_short_and_cites_no_commit():
    text = (REPO / "README.md").read_text()
    assert len(text.splitlines()) <= 300
    prose = LINK.sub("", text)  # link targets may be dated file names
    assert not re.findall(r"\b[0-9a-f]{7,40}\b", prose)
    assert not re.findall(r"\b20\d\d-\d\d-\d\d\b", prose)


def test_every_figure_in_the_readme_results_links_to_a_file_in_docs():
    text = (REPO / "README.md").read_text()
    results = text.split("## Results", 1)[1].split("\n## ", 1)[0]
    rows = [r for r in results.splitlines() if r.startswith("| ") and not r.startswith("| measure")]
    assert rows
    for row in rows:
        for cell in row.strip("|").split("|")[1:]:
            cell = cell.strip()
            if re.search(r"\d", cell):
                assert re.fullmatch(r"\[[^\]]+\]\(docs/[^)]+\)", cell), cell


def test_the_documented_breaks_are_the_mutation_tools():
    """docs/design.md's "Breaks the tests must catch" names every break of
    tools/mutation_check.py, and only those; each names tests that exist."""
    from tools.mutation_check import BREAKS

    text = (REPO / "docs" / "design.md").read_text()
    section = text.split("## Breaks the tests must catch", 1)[1].split("\n## ", 1)[0]
    rows = [r for r in section.splitlines() if r.startswith("| `")]
    documented = {n for r in rows for n in re.findall(r"`([a-z0-9.-]+)`", r.split("|")[1])}
    assert documented == {b.name for b in BREAKS}
    for b in BREAKS:
        for test in b.tests:
            path, _, name = test.partition("::")
            assert (REPO / path).is_file(), test
            assert not name or f"def {name}(" in (REPO / path).read_text(), test
