"""The documentation: the MkDocs site builds without a warning, and the README's links lead somewhere."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

from .conftest import ROOT

MKDOCS = [sys.executable, "-m", "mkdocs", "build", "--strict"]


def _build(root: Path, site: Path) -> subprocess.CompletedProcess:
    return subprocess.run([*MKDOCS, "-f", str(root / "mkdocs.yml"), "-d", str(site)], capture_output=True, text=True)


def test_the_docs_site_builds_in_strict_mode(tmp_path):
    """Every page in the nav, every link and anchor between pages resolves (mkdocs.yml: strict, validation warns)."""
    r = _build(ROOT, tmp_path / "site")
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "site" / "parameters" / "index.html").is_file()


def test_a_broken_link_or_anchor_fails_the_build(tmp_path):
    """The check above can fail: a link to a page that is not there, or to a heading that is not there, stops it."""
    for bad in ("[gone](missing.md)", "[gone](node.md#no-such-heading)"):
        shutil.rmtree(tmp_path / "copy", ignore_errors=True)
        shutil.copytree(ROOT / "docs", tmp_path / "copy" / "docs")
        shutil.copy(ROOT / "mkdocs.yml", tmp_path / "copy")
        with open(tmp_path / "copy" / "docs" / "index.md", "a") as page:
            page.write(f"\n{bad}\n")
        r = _build(tmp_path / "copy", tmp_path / "site")
        assert r.returncode != 0 and bad.split("(")[1].rstrip(")").split("#")[-1] in r.stderr, (bad, r.stderr)


def _slugs(page: Path) -> set[str]:
    """The anchors MkDocs gives a page's headings."""
    return {re.sub(r"[^\w\- ]", "", h.strip().lower()).replace(" ", "-")
            for h in re.findall(r"^#+ (.+)$", page.read_text(), re.M)}


def test_every_link_of_the_readme_leads_to_a_file_and_heading_that_exist():
    links = re.findall(r"\]\(([^)\s]+)\)", (ROOT / "README.md").read_text())
    local = [link for link in links if not link.startswith(("http://", "https://"))]
    assert len(local) >= 10
    for link in local:
        path, _, anchor = link.partition("#")
        assert (ROOT / path).exists(), link
        assert not anchor or anchor in _slugs(ROOT / path), link


def test_the_readme_stays_a_front_page_and_no_page_keeps_a_diary():
    """The README was a 990-line lab notebook with dates, commit hashes and run numbers in its prose."""
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 250
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        text = page.read_text()
        assert not re.search(r"\b20\d\d-\d\d-\d\d\b", text), page  # a date
        assert not re.search(r"\b(at|commit) [0-9a-f]{7,40}\b", text), page  # a commit hash
        assert not re.search(r"\brun \d+\b", text, re.I), page  # a run number


def test_the_architecture_map_names_every_module_in_its_layer():
    """docs/architecture.md's map of the package: each layer's paragraph names each of its modules, so that a new
    module is placed (and a removed one leaves) with the code."""
    block = (ROOT / "docs" / "architecture.md").read_text().split("```")[1]
    layers = dict(re.findall(r"^  (\w+)/ +(.*?)(?=^  \w+/|\Z)", block, re.M | re.S))
    package = ROOT / "nmnet_ros"
    assert set(layers) == {p.parent.name for p in package.glob("*/__init__.py")}, layers.keys()
    for layer, text in layers.items():
        named = set(re.findall(r"\w+", text))
        missing = [m.stem for m in (package / layer).glob("*.py") if m.stem != "__init__" and m.stem not in named]
        assert not missing, f"docs/architecture.md does not place {layer}/{missing}"
