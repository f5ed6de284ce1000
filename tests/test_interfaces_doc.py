"""docs/interfaces.md agrees with the shared INTERFACES.md, which stays the reference.

Every fenced block of the reference (file layouts, the command line, the REST
flow) stands verbatim in the repository's page, so that the page a user reads
cannot drift from the contract the external checks use. CI has the shared
folder beside the clone; elsewhere the test is skipped without it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT.parent / "shared" / "INTERFACES.md"
PAGE = ROOT / "docs" / "interfaces.md"
FENCED = re.compile(r"^```[^\n]*\n(.*?)^```", re.MULTILINE | re.DOTALL)


def test_every_block_of_the_reference_stands_in_docs_interfaces() -> None:
    if not REFERENCE.is_file():
        if os.environ.get("CI"):
            pytest.fail(f"the shared INTERFACES.md is missing at {REFERENCE}")
        pytest.skip(f"the shared INTERFACES.md is not next to this checkout ({REFERENCE})")
    page = PAGE.read_text(encoding="utf-8")
    blocks = FENCED.findall(REFERENCE.read_text(encoding="utf-8"))
    assert len(blocks) >= 5  # the rig file, the command line, markers.csv, result.json, REST
    missing = [block.splitlines()[0] for block in blocks if block not in page]
    assert not missing, f"docs/interfaces.md lacks the blocks starting with: {missing}"


def test_the_docs_point_to_docs_interfaces_not_to_the_shared_folder() -> None:
    pages = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
    bad = [
        str(p.relative_to(ROOT))
        for p in pages
        if re.search(r"INTERFACES\.md|shared folder", p.read_text(encoding="utf-8"))
    ]
    assert not bad, f"these pages point at the shared folder instead of docs/interfaces.md: {bad}"
