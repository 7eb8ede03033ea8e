"""The docs: the README stays short, the site builds with every internal link and anchor
resolved (mkdocs --strict), and every figure the README and docs quote from results/ is what
the results say."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fluxdrive.analysis.quotes import count, fill, format_value, quoted_files, stale

REPO = Path(__file__).resolve().parents[1]


def test_readme_at_most_150_lines():
    n = len((REPO / "README.md").read_text().splitlines())
    assert n <= 150, f"README.md has {n} lines; move the detail into docs/"


def test_readme_links_resolve():
    # the README is not a page of the site, so its relative links are checked here
    text = (REPO / "README.md").read_text()
    links = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    assert links
    missing = [t for t in links if "://" not in t and not (REPO / t).exists()]
    assert missing == []


def test_site_builds_strict(tmp_path):
    # --strict turns every warning into a failure: links to missing pages, missing anchors,
    # pages left out of the nav, docstrings the API reference cannot render
    r = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "-d", str(tmp_path / "site")],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr[-3000:]
    assert (tmp_path / "site" / "index.html").exists()
    assert (tmp_path / "site" / "api.html").exists()


def test_quoted_figures_are_current():
    files = quoted_files()
    assert count(files) >= 10  # the README's result table at least
    assert stale(files) == [], "run ./fluxdrive docs quotes"


def test_parameter_tables_are_current():
    """docs/configuration.md's, docs/study.md's, docs/graph.md's graph-file and
    docs/machines.md's identify tables are what the schemas generate."""
    from fluxdrive.drive.config_blocks import stale_tables
    from fluxdrive.io import graphfile
    from fluxdrive.study import spec

    assert stale_tables() == [], "run ./fluxdrive docs params"
    assert stale_tables(spec.docs_tables(), spec.DOC_PAGE) == [], "run ./fluxdrive docs params"
    graph = stale_tables(graphfile.docs_tables(), graphfile.DOC_PAGE)
    assert graph == [], "run ./fluxdrive docs params"
    from fluxdrive.drive import identify

    ident = stale_tables(identify.docs_tables(), identify.DOC_PAGE)
    assert ident == [], "run ./fluxdrive docs params"


def test_node_parameter_tables_are_current():
    """docs/graph.md's node tables are what the nodes declare (started without a graph)."""
    pytest.importorskip("rclpy")
    from fluxdrive_bringup.inspect import paramdoc

    text = paramdoc.PAGE.read_text()
    assert paramdoc.fill(text) == text, "run ./fluxdrive docs params"


def test_quote_fill_reads_the_results(tmp_path):
    (tmp_path / "r.json").write_text(json.dumps({"a": {"rms": [2.0, 2.5, 2.25], "n": 7}}))
    text = (
        "x <!-- quote r.json a.rms range:.1f -->old<!-- /quote --> y "
        "<!-- quote r.json a.n d -->?<!-- /quote -->"
    )
    out = fill(text, results_dir=tmp_path)
    assert "-->2.0–2.5<!--" in out and "-->7<!--" in out
    assert format_value([1.234, 1.236], "range:.2f") == "1.23–1.24"
    assert format_value([1.231, 1.234], "range:.2f") == "1.23"
