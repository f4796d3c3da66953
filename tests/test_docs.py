"""The documentation: the API reference covers the public names; the README stays a front door."""

import re
from pathlib import Path

import torch_api

ROOT = Path(__file__).resolve().parents[1]


def test_the_api_reference_covers_every_public_name():
    page = (ROOT / "docs" / "reference" / "api.md").read_text()
    documented = set(re.findall(r"^::: torch_api\.(\w+)$", page, flags=re.MULTILINE))
    assert documented == set(torch_api.__all__)


def test_every_page_of_the_docs_is_in_the_site_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    pages = {
        str(p.relative_to(ROOT / "docs"))
        for p in (ROOT / "docs").rglob("*.md")
        if "data" not in p.parts
    }
    missing = sorted(p for p in pages if p not in nav)
    assert not missing, f"pages outside the navigation: {missing}"


def test_the_readme_is_a_front_door():
    text = (ROOT / "README.md").read_text()
    lines = text.splitlines()
    assert len(lines) <= 250
    outside_citation = text.split("## How to cite")[0]
    assert not re.findall(r"20[0-9]{2}-[0-9]{2}-[0-9]{2}", outside_citation)
    start = next(i for i, line in enumerate(lines) if "results:start" in line)
    assert start < 120, "the headline results table must be within the first 120 lines"
