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
    assert len(readme.read_text().splitlines()) <= 400
    for page in (readme, ROOT / "docs" / "guide.md", ROOT / "experiments" / "README.md"):
        for target, anchor in LINK.findall(page.read_text()):
            if target.startswith(("http://", "https://")):
                continue
            path = (page.parent / target) if target else page
            assert path.exists(), f"{page.name} links to {target}, which does not exist"
            if anchor and path.suffix == ".md":
                assert anchor in anchors_of(path), f"{page.name} links to {target}#{anchor}, no such heading"


def test_every_result_folder_says_how_it_was_made():
    """results/ holds only frozen snapshots: each folder has a README and a manifest naming the command,
    commit, machine and date (scripts/manifest.py); nothing lies loose at its top."""
    import json

    results = ROOT / "results"
    loose = [p.name for p in results.iterdir() if p.is_file()]
    assert not loose, f"files at the top of results/: {loose}; put them in a folder with a manifest"
    for folder in (p for p in results.iterdir() if p.is_dir()):
        assert (folder / "README.md").is_file(), f"{folder.name} has no README.md"
        manifest = json.loads((folder / "manifest.json").read_text())
        missing = [k for k in ("command", "commit", "date", "machine") if not manifest.get(k)]
        assert not missing, f"{folder.name}/manifest.json lacks {missing}"
