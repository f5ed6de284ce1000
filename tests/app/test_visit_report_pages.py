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


def test_a_wrong_signing_password_comes_back_to_the_session_page_with_the_error_by_the_field(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    """A clinic day ended on a "Not allowed" page whose only link led to the patient list."""
    csrf = login(client)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    r = client.post(
        f"/sessions/{session_id}/sign",
        data={"csrf_token": csrf, "password": "not my password"},
        follow_redirects=False,
    )
    assert r.status_code == 403
    assert "Not allowed" not in r.text and "Return to the patient list" not in r.text
    form = re.search(r"<form [^>]*data-sign-form>.*?</form>", r.text, re.S)
    assert form, "the session page's signing form is not there"
    field = re.search(r'<input id="sign-password"[^>]*>', form.group(0)).group(0)
    assert 'aria-describedby="sign-error"' in field and 'aria-invalid="true"' in field
    error = re.search(r'<p class="form-error" id="sign-error"[^>]*>([^<]+)</p>', form.group(0))
    assert error and "The password is wrong" in error.group(1)
    assert "Upload the left hand" in r.text  # the whole session page, not a stub
    assert "Visit signed" not in r.text
