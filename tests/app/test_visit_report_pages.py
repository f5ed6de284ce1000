"""After signing, the pages offer the signed visit report, and a copy made later says it is
not the signed record (a neurologist found it byte for byte the unsigned one)."""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
from test_pages import PASSWORD, client, login, seeded  # noqa: F401 - fixtures

from app.models import Trial


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
def test_after_signing_the_pages_offer_the_signed_copy_and_the_live_one_says_so(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    tmp_path,
):
    csrf = login(client)
    trial_id = seeded["trials"][(1, "right")]
    with db_sessionmaker() as db:
        session_id = db.get(Trial, trial_id).session_id
    live = f"/sessions/{session_id}/visit-report.pdf"
    before = client.get(live).content
    assert "signed/" not in client.get(f"/sessions/{session_id}").text
    r = client.post(
        f"/sessions/{session_id}/sign",
        data={"csrf_token": csrf, "password": PASSWORD},
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text[:500]
    after = client.get(live).content
    assert after != before  # no longer the unmarked copy of before the signature
    path = tmp_path / "live.pdf"
    path.write_bytes(after)
    page1 = subprocess.run(
        ["pdftotext", "-f", "1", "-l", "1", str(path), "-"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    page1 = " ".join(page1.split())
    assert "Not the signed record. This visit was signed as signature 1" in page1
    assert f"/sessions/{session_id}/signed/1.pdf" in page1.replace("/ ", "/")  # wrapped
    # The session and the trial pages offer the signed copy, and say which is which.
    for url in (f"/sessions/{session_id}", f"/trials/{trial_id}"):
        html = client.get(url).text
        link = re.search(r'<a class="button" href="([^"]+)" data-signed-report="1">', html)
        assert link and link.group(1) == f"/sessions/{session_id}/signed/1.pdf", url
        assert "Visit report as it is now (not signed" in html, url
    signed = client.get(f"/sessions/{session_id}/signed/1.pdf")
    assert signed.status_code == 200 and signed.content.startswith(b"%PDF")
