"""Published numbers: every table in the README and the docs is the rendering of a stored result with provenance."""

from __future__ import annotations

import hashlib
import json
import re
import sys

import pytest

from .conftest import ROOT

sys.path.insert(0, str(ROOT))
import benchmarks  # noqa: E402 - the repository's benchmarks/ folder, not an installed package

STORED = sorted(benchmarks.RESULTS.glob("*.json"))


def test_every_published_table_is_its_stored_result():
    """Change a number in a page, or a stored result without rendering it, and this fails
    (`python -m benchmarks render` rewrites the tables)."""
    blocks = 0
    for page in benchmarks.PAGES:
        text = page.read_text()
        blocks += len(benchmarks.BLOCK.findall(text))
        assert benchmarks.render_page(text) == text, f"{page.relative_to(ROOT)}: run python -m benchmarks render"
    own = [name for name, e in benchmarks.EXPERIMENTS.items() if e.render is not None]
    assert blocks >= len(own) + len(benchmarks.COMBINED)  # each table once at least


def test_every_experiment_is_stored_with_its_provenance_for_the_shipped_weights():
    """A result records how to rerun it and what it ran on; one from other weights than those shipped is stale."""
    shipped = hashlib.sha256(benchmarks.WEIGHTS.read_bytes()).hexdigest()
    assert {p.stem for p in STORED} == set(benchmarks.EXPERIMENTS)
    published = "".join(page.read_text() for page in benchmarks.PAGES)
    for path in STORED:
        stored = json.loads(path.read_text())
        p = stored["provenance"]
        assert p["command"].startswith("nmnet ") and re.fullmatch(r"[0-9a-f]{40}", p["commit"]), path
        assert p["weights_sha256"] == shipped, f"{path.name}: measured with other weights; rerun it"
        assert {"cpu", "cores"} <= set(p["machine"]) and p["date"] and p["settings"], path
        shown_in = [f"<!-- benchmark: {path.stem} -->"] + [f"<!-- benchmark: {name} -->" for name, (parts, _) in
                                                            benchmarks.COMBINED.items() if path.stem in parts]
        assert any(block in published for block in shown_in), f"{path.name} is published nowhere"


@pytest.mark.slow
def test_one_command_runs_an_experiment_and_stores_it(tmp_path, monkeypatch):
    """`python -m benchmarks run sample-bag`, into a scratch results folder: the replay's summary, with provenance."""
    monkeypatch.setattr(benchmarks, "RESULTS", tmp_path)
    path = benchmarks.run("sample-bag")
    stored = json.loads(path.read_text())
    assert stored["experiment"] == "sample-bag" and stored["provenance"]["command"].startswith("nmnet replay nmnet_ros/")
    assert stored["result"]["processed"] == 40 and stored["result"]["baseline"]["auc5"] is not None
    assert "| learned: NM-Net" in benchmarks.rendered("sample-bag")
