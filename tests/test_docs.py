"""The documentation users get is the documentation rtsgt points at.

Every reference to ``docs/<file>.md`` (with or without ``#section``) in the package, the README,
the examples, the tests and the docs themselves names a file of the repository and, where a
section is given, one of its headings (GitHub's anchors: lower case, punctuation dropped,
spaces as hyphens). Nothing cites the design notes the repository does not carry, or a folder
beside the checkout. A simulated deployment's TOML points at documentation that exists.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from _paths import EXAMPLE_TOML, REPO

DOCS = REPO / "docs"
TEXT_FILES = sorted(
    [*REPO.joinpath("src").rglob("*.py"), *REPO.joinpath("tests").rglob("*.py"),
     *REPO.joinpath("benchmarks").rglob("*.py"), *DOCS.rglob("*.md"), REPO / "README.md",
     EXAMPLE_TOML]
)
REFERENCE = re.compile(r"(?:docs/)?([a-z0-9-]+\.md)(?:#([a-z0-9-]+))?")


def anchors(md: Path) -> set[str]:
    """GitHub's anchors of the headings of a Markdown file."""
    out = set()
    for line in md.read_text(encoding="utf-8").splitlines():
        m = re.match(r"#+\s+(.*)", line)
        if m:
            title = re.sub(r"[^\w\- ]", "", m[1].strip().lower())
            out.add(title.replace(" ", "-"))
    return out


def doc_references(path: Path) -> list[tuple[str, str | None]]:
    text = path.read_text(encoding="utf-8")
    refs = []
    for m in re.finditer(r"docs/[a-z0-9-]+\.md(?:#[a-z0-9-]+)?", text):
        name, section = REFERENCE.fullmatch(m[0]).groups()
        refs.append((name, section))
    if path.parent == DOCS:  # links between the docs pages: (file.md#section)
        for m in re.finditer(r"\]\(([a-z0-9-]+\.md)(?:#([a-z0-9-]+))?\)", text):
            refs.append((m[1], m[2]))
    return refs


def test_the_docs_exist():
    names = {p.name for p in DOCS.glob("*.md")}
    assert {"README.md", "noise-model.md", "conventions.md", "file-formats.md",
            "paper-figures.md"} <= names


@pytest.mark.parametrize("path", TEXT_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_references_to_the_docs_resolve(path):
    for name, section in doc_references(path):
        target = DOCS / name
        assert target.is_file(), f"{path}: docs/{name} does not exist"
        if section:
            assert section in anchors(target), f"{path}: docs/{name} has no section #{section}"


@pytest.mark.parametrize("path", TEXT_FILES, ids=lambda p: str(p.relative_to(REPO)))
def test_nothing_cites_files_users_do_not_have(path):
    text = path.read_text(encoding="utf-8")
    if path.name in ("test_docs.py",):
        return
    assert "DESIGN.md" not in text, path
    assert "../shared" not in text and "shared/data" not in text, path


def test_a_simulated_deployment_points_at_existing_documentation():
    from rtsgt.simulation import SimulationConfig, simulate_deployment
    from rtsgt.simulation.files import _toml_text

    sim = simulate_deployment(SimulationConfig(duration_s=30.0), np.random.default_rng(0))
    text = _toml_text(sim, "t")
    assert "README, section" not in text
    refs = re.findall(r"docs/[a-z0-9-]+\.md", text)
    assert refs, "the filter gates' comment should say where the reason is documented"
    for ref in refs:
        assert (REPO / ref).is_file(), ref
