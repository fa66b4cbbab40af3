"""The README stays a guide a newcomer reads in ten minutes, and its links lead somewhere."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\]\(([^)#\s]*)(?:#([^)\s]+))?\)")


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


def anchors_of(path: Path) -> set[str]:
    return {github_anchor(line.lstrip("#")) for line in path.read_text().splitlines() if line.startswith("#")}


def test_github_anchor():
    assert github_anchor("Baselines: ProtoNets, MAML and frozen pretrained features") == \
        "baselines-protonets-maml-and-frozen-pretrained-features"
    assert github_anchor("The format (version 1)") == "the-format-version-1"


def test_the_readme_is_short_and_every_local_link_resolves():
    readme = ROOT / "README.md"
    lines = readme.read_text().splitlines()
    assert len(lines) <= 150
    assert any("own images" in line.lower() for line in lines[:60]), "the README says how to use one's own images early"
    pages = [readme, ROOT / "lab" / "README.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "results").glob("*/README.md"))]
    for page in pages:
        for target, anchor in LINK.findall(page.read_text()):
            if target.startswith(("http://", "https://")):
                continue
            path = (page.parent / target) if target else page
            assert path.exists(), f"{page.relative_to(ROOT)} links to {target}, which does not exist"
            if anchor and path.suffix == ".md":
                assert anchor in anchors_of(path), f"{page.relative_to(ROOT)} links to {target}#{anchor}, no such heading"


def test_results_hold_what_the_docs_show_within_their_budget():
    """results/ is a few folders of small tables and figures, each with a README and a manifest naming the
    command, commit, machine and date (scripts/manifest.py); nothing lies loose at its top."""
    import json

    results = ROOT / "results"
    loose = [p.name for p in results.iterdir() if p.is_file()]
    assert not loose, f"files at the top of results/: {loose}; put them in a folder with a manifest"
    folders = [p for p in results.iterdir() if p.is_dir()]
    assert len(folders) <= 12, f"{len(folders)} result folders; the budget is 12"
    size = sum(f.stat().st_size for f in results.rglob("*") if f.is_file())
    assert size <= 8 * 2**20, f"results/ holds {size / 2**20:.1f} MiB; the budget is 8"
    for folder in folders:
        assert (folder / "README.md").is_file(), f"{folder.name} has no README.md"
        manifest = json.loads((folder / "manifest.json").read_text())
        missing = [k for k in ("command", "commit", "date", "machine") if not manifest.get(k)]
        assert not missing, f"{folder.name}/manifest.json lacks {missing}"


def test_the_project_speaks_of_itself_only():
    """No tracked file speaks of the working periods that made it (the word below): a result is named by its date
    and the command that makes it."""
    import subprocess

    if not (ROOT / ".git").exists():
        import pytest

        pytest.skip("not a git checkout")
    found = subprocess.run(["git", "grep", "-n", "-i", "-w", "-E", "sess" + "ions?"], cwd=ROOT, capture_output=True,
                           text=True).stdout
    assert not found, found[:2000]
