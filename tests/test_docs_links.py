"""The guide's and the docs' links to files of the repository resolve (pictures included)."""
from __future__ import annotations

import re

from .conftest import ROOT

LINK = re.compile(r"\]\(([^)\s]+)\)")


def test_every_relative_link_of_the_guide_and_docs_points_to_a_file():
    pages = [ROOT / "README.md", ROOT / "results" / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    assert len(pages) > 5
    broken = []
    for page in pages:
        for target in LINK.findall(page.read_text()):
            if re.match(r"[a-z]+:", target) or target.startswith("#"):
                continue  # a web address or a heading on the same page
            path = (page.parent / target.split("#")[0]).resolve()
            if not path.exists():
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, "links to missing files:\n" + "\n".join(broken)
