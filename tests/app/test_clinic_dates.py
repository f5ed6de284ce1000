"""Labels name the clinic's day and the task's limb: a late session is not dated the UTC day
before, and toe tapping's medication response is not headed "right hand"."""

from __future__ import annotations

import dataclasses
import html as html_lib
import re
from datetime import UTC, datetime

from fastapi.testclient import TestClient
from sample_trial import sample_report_data, task_trial
from test_pages import login, seeded  # noqa: F401 - fixture

from app.models import RecordingSession, Trial
from app.reports.rendering import render_visit_html
from app.reports.visit import SessionFacts, VisitData
from app.web.results import trial_label
from core.version import software_version

LATE = datetime(2026, 3, 1, 23, 30, tzinfo=UTC)  # 00:30 on 2 March in Prague (CET)


def test_a_trial_is_labelled_with_the_clinic_s_day():
    trial = Trial(hand="right", task="toe_tapping")
    trial.session = RecordingSession(recorded_at=LATE, medication_state="off")
    assert trial_label(trial, "Europe/Prague") == "2026-03-02, right foot, medication off"
    assert trial_label(trial, "UTC") == "2026-03-01, right foot, medication off"


def test_the_session_and_trial_pages_date_a_late_session_on_the_clinic_s_day(
    app_settings,
    seeded,  # noqa: F811
    db_sessionmaker,
):
    from app.main import create_app

    right, left = seeded["trials"][(1, "right")], seeded["trials"][(1, "left")]
    with db_sessionmaker() as db:
        session = db.get(Trial, right).session
        session.recorded_at = LATE
        session_id = session.id
        db.commit()
    prague = app_settings.model_copy(update={"timezone": "Europe/Prague"})
    with TestClient(create_app(prague)) as client:
        login(client)
        title = re.search(r"<title>(.*?)</title>", client.get(f"/sessions/{session_id}").text)
        assert "Session 2026-03-02" in title.group(1)
        page = html_lib.unescape(client.get(f"/trials/{right}").text)
        assert "2026-03-02, right hand, medication on" in page  # the title and the labels
        assert "2026-03-01, right hand" not in page
        assert re.search(rf'<option value="{left}"[^>]*>2026-03-02, left hand', page)


def test_the_medication_response_is_headed_by_the_task_s_limb():
    base = sample_report_data()
    _, doc, _ = task_trial("toe_tapping")
    trials = tuple(
        dataclasses.replace(
            base, trial_id=20 + i, task="toe_tapping", medication_state=med, result=doc
        )
        for i, med in enumerate(("off", "on"))
    )
    visit = VisitData(
        patient_code="PD-0042",
        session_id=1,
        visit_date=base.recorded_at.date(),
        timezone="UTC",
        sessions=(SessionFacts(1, base.recorded_at, "off", "none"),),
        trials=trials,
        software_version=software_version(),
    )
    html = render_visit_html(visit)
    table = re.search(r"<table class=\"compact\" data-medication>.*?</table>", html, re.S).group(0)
    assert '<th scope="col" class="num">right foot</th>' in table
    assert "right hand" not in table
