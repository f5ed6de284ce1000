# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""``HEAD`` on a trial's PDF report answers its headers without making the report.

The PDF is made ahead of time by the worker and kept in the report cache; when it is
not there yet, the ``GET`` makes it (a second or more of WeasyPrint's CPU). ``HEAD``
made it too, only for the server to throw the body away: a client checking a link
cost as much as a download.
"""

from __future__ import annotations

import pytest
from api_support import Api, api, video_pair  # noqa: F401 - fixtures
from pdf_head_checks import head_after_made, head_before_made
from sqlalchemy import select
from test_revisions import _trial

from app.models import AuditEvent
from app.services import results as results_service


@pytest.fixture
def measured(api: Api, video_pair) -> int:
    return _trial(api, video_pair)  # a result, and no report job run: the PDF is not made


@pytest.fixture
def renders(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The trials whose PDF report is made, in order (the real renderer still runs)."""
    made: list[int] = []
    real = results_service.render_report_pdf

    def counted(data):
        made.append(data.trial_id)
        return real(data)

    monkeypatch.setattr(results_service, "render_report_pdf", counted)
    return made


def _exports(api: Api, trial_id: int) -> int:
    with api.sessions() as db:
        return len(
            db.scalars(
                select(AuditEvent).where(
                    AuditEvent.action == "export",
                    AuditEvent.resource_type == "report_pdf",
                    AuditEvent.resource_id == str(trial_id),
                )
            ).all()
        )


def test_head_of_a_report_not_made_yet_does_not_make_it(
    api: Api, measured: int, renders: list[int]
) -> None:
    url = f"/api/v1/trials/{measured}/report.pdf"
    head_before_made(api, url, measured, renders, lambda: _exports(api, measured))


def test_head_of_a_report_made_gives_the_gets_headers(
    api: Api, measured: int, renders: list[int]
) -> None:
    url = f"/api/v1/trials/{measured}/report.pdf"
    other = f"/api/v1/trials/{measured + 1}/report.pdf"
    head_after_made(api, url, measured, renders, lambda: _exports(api, measured), other)
