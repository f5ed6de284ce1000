"""After signing, the pages offer the signed visit report, and a copy made later says it is
not the signed record (a neurologist found it byte for byte the unsigned one)."""

from __future__ import annotations

import html as html_lib
import re
import shutil
import subprocess

import pytest
from test_pages import PASSWORD, client, login, seeded  # noqa: F401 - fixtures

from app.models import Job, Trial


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
    described = re.search(r'aria-describedby="([^"]+)"', field).group(1).split()
    assert "sign-error" in described and 'aria-invalid="true"' in field
    error = re.search(r'<p class="form-error" id="sign-error"[^>]*>([^<]+)</p>', form.group(0))
    assert error and "The password is wrong" in error.group(1)
    assert "Upload the left hand" in r.text  # the whole session page, not a stub
    assert "Visit signed" not in r.text


def _failed_take(db, session_id: int, task: str, hand: str, status: str = "failed") -> int:
    trial = Trial(session_id=session_id, task=task, hand=hand, status=status)
    db.add(trial)
    db.flush()
    error = WHY if status == "failed" else None
    db.add(Job(kind="analyze_trial", trial_id=trial.id, status=status, error=error))
    return trial.id


WHY = "no marker was seen consistently by both cameras; check that both cameras see them"


def _pdf_text(pdf: bytes, tmp_path) -> str:
    path = tmp_path / "signed.pdf"
    path.write_bytes(pdf)
    text = subprocess.run(["pdftotext", str(path), "-"], check=True, capture_output=True, text=True)
    return " ".join(text.stdout.split())


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
def test_the_sign_form_warns_and_the_signed_report_lists_failed_and_pending_trials(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    tmp_path,
):
    """Session 7's failed pronation-supination trial was silently left out of the signed
    report, and the sign form said nothing of it nor of the unrated side (item 3)."""
    csrf = login(client)
    left = seeded["trials"][(1, "left")]  # measured, not rated
    with db_sessionmaker() as db, db.begin():
        session_id = db.get(Trial, left).session_id
        failed = _failed_take(db, session_id, "pronation_supination", "right")
        pending = _failed_take(db, session_id, "finger_tapping", "left", "running")
    page = client.get(f"/sessions/{session_id}").text
    box = re.search(r"<div [^>]*data-sign-warnings>.*?</div>", page, re.S)
    assert box, "no warning before signing"
    text = " ".join(re.sub(r"<[^>]+>", " ", html_lib.unescape(box.group(0))).split())
    assert (
        f"1 trial failed and will be listed in the signed report as not measured, with why:"
        f" #{failed} (pronation–supination, right hand, medication on)." in text
    )
    assert "1 trial is still being measured" in text and f"#{pending} (finger tapping" in text
    assert "1 trial has no rating of yours yet" in text and f"#{left} (finger tapping, left" in text
    field = re.search(r'<input id="sign-password"[^>]*>', page).group(0)
    assert "sign-warnings" in field  # read with the password field

    r = client.post(
        f"/sessions/{session_id}/sign",
        data={"csrf_token": csrf, "password": PASSWORD},
        follow_redirects=False,
    )
    assert r.status_code == 303, r.text[:300]  # warned, not refused
    signed = _pdf_text(client.get(f"/sessions/{session_id}/signed/1.pdf").content, tmp_path)
    assert "Trials without a result (not reported)" in signed
    assert f"Trial #{failed}: pronation–supination, right hand, medication on, uploaded" in signed
    assert f"the measurement failed: {WHY}" in signed
    assert f"Trial #{pending}: finger tapping, left hand" in signed
    assert "still being measured when this report was made" in signed

    # A take that fails after the signature is a change of what the signed report listed.
    with db_sessionmaker() as db, db.begin():
        late = _failed_take(db, session_id, "hand_movements", "left")
        db.get(Trial, pending).status = "failed"
    state = client.get(f"/sessions/{session_id}").text
    assert 'data-signing="amendment_pending"' in state
    assert f"trial {late} was added (its measurement failed)" in state
    assert f"the measurement of trial {pending} failed" in state


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
def test_the_summary_footnote_says_how_bands_are_read_without_a_developer_path(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
    tmp_path,
):
    """ "(docs/metrics.md)" was printed to clinicians on the result page and the signed PDF."""
    login(client)
    trial_id = seeded["trials"][(1, "right")]
    with db_sessionmaker() as db:
        session_id = db.get(Trial, trial_id).session_id
    words = (
        "Bands are the MDS-UPDRS wording the counts fall into — interruptions from the"
        " hesitations and halts counted, decrement from the tap after which the amplitude"
        " starts to fall — shown as evidence beside your own rating"
    )
    page = client.get(f"/trials/{trial_id}").text
    note = re.search(r'<p class="summary-note">(.*?)</p>', page, re.S).group(1)
    assert words in " ".join(html_lib.unescape(note).split()) and "docs/" not in note
    pdf = _pdf_text(client.get(f"/sessions/{session_id}/visit-report.pdf").content, tmp_path)
    assert words in pdf and "docs/" not in pdf


def _page_warnings(page: str) -> list[str]:
    box = re.search(r"<div [^>]*data-sign-warnings>.*?</div>", page, re.S)
    items = re.findall(r"<li>(.*?)</li>", box.group(0), re.S) if box else []
    return [" ".join(html_lib.unescape(re.sub(r"<[^>]+>", " ", i)).split()) for i in items]


def test_the_api_tells_an_integrator_what_the_sign_form_warns_of(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    """The page's sign form names failed, pending and unrated trials before signing; the
    API's signing state and its answer to signing said none of it, so a hospital system
    asking for the password showed nothing. Both now carry the form's very sentences."""
    csrf = login(client)
    headers = {"X-CSRF-Token": csrf}
    left = seeded["trials"][(1, "left")]  # measured, not rated
    with db_sessionmaker() as db, db.begin():
        session_id = db.get(Trial, left).session_id
        failed = _failed_take(db, session_id, "pronation_supination", "right")
        pending = _failed_take(db, session_id, "finger_tapping", "left", "running")
        other_visit = db.get(Trial, seeded["trials"][(0, "right")]).session_id  # rated
    state = client.get(f"/api/v1/sessions/{session_id}/signatures", headers=headers)
    assert state.status_code == 200, state.text
    warnings = state.json()["warnings"]
    assert warnings == _page_warnings(client.get(f"/sessions/{session_id}").text)
    assert len(warnings) == 3 and all(f"#{t} (" in " ".join(warnings)
                                      for t in (failed, pending, left))  # fmt: skip
    assert warnings[0].startswith("1 trial failed and will be listed in the signed report")
    quiet = client.get(f"/api/v1/sessions/{other_visit}/signatures", headers=headers).json()
    assert quiet["warnings"] == [] and quiet["status"] == "unsigned"

    signed = client.post(f"/api/v1/sessions/{session_id}/sign", json={"password": PASSWORD},
                         headers=headers)  # fmt: skip
    assert signed.status_code == 201, signed.text  # warned, not refused
    assert signed.json()["warnings"] == warnings and signed.json()["number"] == 1
    # rated since: the state says what is left
    r = client.patch(f"/api/v1/trials/{left}", json={"clinician_rating": 1}, headers=headers)
    assert r.status_code == 200, r.text
    after = client.get(f"/api/v1/sessions/{session_id}/signatures", headers=headers).json()
    assert after["status"] == "amendment_pending"
    assert after["warnings"] == warnings[:2] and "no rating" not in " ".join(after["warnings"])
