"""The documentation under docs/ is the project's own and every pointer into it resolves.

* No file of src/, tests/, conf/ or README.md refers to a document that is not in the repository
  (the internal reference the project was first built from); they point into docs/ instead.
* Every ``docs/<page>.md`` and ``docs/<page>.md#anchor`` named in src/, tests/, conf/, README.md or
  docs/ (and every relative Markdown link inside docs/) names a page that exists and a heading of it.
* The README links every page of docs/.
"""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = REPO / "docs"
# the name of that outside reference, spelt so that this file does not contain it
OUTSIDE_REFERENCE = "SP" + "EC"
SEARCHED = ("src", "tests", "conf", "README.md")
TEXT_SUFFIXES = (".py", ".yaml", ".yml", ".md", ".toml", ".ipynb", ".txt", ".cfg", ".sh")


def _files(*roots: str) -> list[Path]:
    out = []
    for root in roots:
        path = REPO / root
        if path.is_file():
            out.append(path)
        else:
            out += [p for p in path.rglob("*") if p.suffix in TEXT_SUFFIXES and "__pycache__" not in p.parts]
    return sorted(out)


def slug(heading: str) -> str:
    """GitHub's anchor of a Markdown heading: lower case, punctuation dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    """The anchors of every heading of a Markdown page (outside code fences), with GitHub's -1, -2 ... for repeats."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in page.read_text().splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        match = None if fenced else re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            base = slug(match.group(1))
            n = seen.get(base, 0)
            out.add(base if n == 0 else f"{base}-{n}")
            seen[base] = n + 1
    return out


def test_slug_follows_github():
    assert slug("SO(3) HEALPix grid") == "so3-healpix-grid"
    assert slug("Keys of metrics.json") == "keys-of-metricsjson"
    assert slug("What `dataset=X` alone resolves to") == "what-datasetx-alone-resolves-to"
    assert slug("PASCAL3D+ release 1.1") == "pascal3d-release-11"


def test_no_reference_to_a_document_outside_the_repository():
    """The same check as ``grep -rn <name> src tests conf README.md``, which must find nothing."""
    proc = subprocess.run(["grep", "-rn", OUTSIDE_REFERENCE, *SEARCHED], cwd=REPO, capture_output=True, text=True)
    hits = [line for line in proc.stdout.splitlines() if "__pycache__" not in line and "Binary file" not in line]
    assert proc.returncode in (0, 1), proc.stderr
    assert not hits, "point these into docs/ instead:\n" + "\n".join(hits)


POINTER = re.compile(r"docs/([\w\-]+\.md)(?:#([\w\-]+))?")
LINK = re.compile(r"\]\(([^)\s#]*\.md)?(?:#([\w\-]+))?\)")


def pointers() -> list[tuple[str, str, str | None]]:
    """``(where, page, anchor)`` of every pointer into docs/ in the searched files and in docs/."""
    found = []
    for path in _files(*SEARCHED, "docs"):
        rel = path.relative_to(REPO).as_posix()
        for number, line in enumerate(path.read_text(errors="replace").splitlines(), 1):
            for page, anchor in POINTER.findall(line):
                found.append((f"{rel}:{number}", page, anchor or None))
            if path.parent == DOCS:  # relative links between pages, and to headings of the same page
                for target, anchor in LINK.findall(line):
                    if target and ("/" in target or target.startswith("..")):
                        continue  # links out of docs/ (to the README, to modules) are checked below
                    found.append((f"{rel}:{number}", target or path.name, anchor or None))
    return found


def test_every_pointer_into_docs_resolves():
    found = pointers()
    assert len({p for _, p, _ in found}) >= 4, "expected pointers to several pages of docs/"
    broken = []
    for where, page, anchor in found:
        target = DOCS / page
        if not target.is_file():
            broken.append(f"{where}: docs/{page} does not exist")
        elif anchor and anchor not in anchors(target):
            broken.append(f"{where}: docs/{page} has no heading with the anchor #{anchor}")
    assert not broken, "\n".join(broken)


def test_relative_links_out_of_docs_resolve():
    """Links from docs/ to modules and to the README (``../src/...``) name files that exist."""
    broken = []
    for page in sorted(DOCS.glob("*.md")):
        for number, line in enumerate(page.read_text().splitlines(), 1):
            for target in re.findall(r"\]\((\.\./[^)\s#]+)(?:#[^)]*)?\)", line):
                if not (DOCS / target).resolve().exists():
                    broken.append(f"docs/{page.name}:{number}: {target}")
    assert not broken, "\n".join(broken)


@pytest.mark.parametrize("page", sorted(p.name for p in DOCS.glob("*.md")))
def test_readme_links_every_page(page):
    assert f"](docs/{page})" in (REPO / "README.md").read_text(), f"README.md does not link docs/{page}"


def test_the_checks_can_fail(tmp_path):
    """A missing page and a missing heading are both reported (on a page written here)."""
    page = tmp_path / "p.md"
    page.write_text("# Title\n\n## Same\n\n## Same\n\n```\n# not a heading\n```\n")
    assert anchors(page) == {"title", "same", "same-1"}
    assert "not-a-heading" not in anchors(page)
