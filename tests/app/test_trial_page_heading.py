"""The trial page's heading names the task, the side and the trial by its upload time.

It said the patient, the side and the session's date only, so two takes of one task
and side in a visit had the same heading; the review page and the reports already
name a trial by its number and upload time (app.reports.visit.trial_time).
"""

from __future__ import annotations

import html as html_lib
import re
from datetime import UTC, datetime

from test_pages import client, login, seeded  # noqa: F401 - fixtures

from app.models import Trial


def _h1(page: str) -> str:
    found = re.search(r"<h1>(.*?)</h1>", page, re.S)
    assert found, "the page has no <h1>"
    return " ".join(html_lib.unescape(re.sub(r"<[^>]+>", " ", found.group(1))).split())


def _title(page: str) -> str:
    found = re.search(r"<title>(.*?)</title>", page, re.S)
    assert found, "the page has no <title>"
    return html_lib.unescape(found.group(1))


def test_two_takes_of_one_task_and_side_have_headings_of_their_own(
    client,  # noqa: F811
    seeded,  # noqa: F811
    db_sessionmaker,
):
    login(client)
    first, second = seeded["trials"][(1, "right")], seeded["trials"][(1, "left")]
    with db_sessionmaker() as db:
        db.get(Trial, first).created_at = datetime(2025, 3, 1, 9, 2, tzinfo=UTC)
        again = db.get(Trial, second)  # a second take of the right hand, same session
        again.hand = "right"
        again.created_at = datetime(2025, 3, 1, 9, 7, tzinfo=UTC)
        db.commit()
        assert again.session_id == db.get(Trial, first).session_id
        assert again.task == db.get(Trial, first).task

    headings, titles = {}, {}
    for t, minute in ((first, 2), (second, 7)):
        page = client.get(f"/trials/{t}")
        assert page.status_code == 200, page.text[:300]
        heading = _h1(page.text)
        assert heading == (
            f"PD-0042 — Finger tapping, right hand — trial #{t}, uploaded 2025-03-01 09:{minute:02d} UTC"
        ), heading
        headings[t], titles[t] = heading, _title(page.text)
        assert f"trial {t}, finger tapping, " in titles[t], titles[t]
    assert headings[first] != headings[second]
    assert titles[first] != titles[second]  # two browser tabs read apart too
