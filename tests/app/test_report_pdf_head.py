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
    head = api.client.head(url, headers=api.headers)
    assert head.status_code == 200, head.text
    assert renders == []  # not made for a HEAD
    assert head.content == b""
    assert head.headers["content-type"] == "application/pdf"
    # Its length is known only once made: none is sent rather than a wrong one (0).
    assert "content-length" not in head.headers
    assert _exports(api, measured) == 1  # audited as the GET is

    got = api.client.get(url, headers=api.headers)
    assert got.status_code == 200 and got.content.startswith(b"%PDF")
    assert renders == [measured]  # the GET made it: it was not in the cache before
    assert head.headers["content-disposition"] == got.headers["content-disposition"]


def test_head_of_a_report_made_gives_the_gets_headers(
    api: Api, measured: int, renders: list[int]
) -> None:
    url = f"/api/v1/trials/{measured}/report.pdf"
    got = api.client.get(url, headers=api.headers)
    assert got.status_code == 200, got.text
    head = api.client.head(url, headers=api.headers)
    assert head.status_code == 200, head.text
    assert renders == [measured]  # made once, by the GET
    assert head.content == b""
    for header in ("content-type", "content-length", "content-disposition"):
        assert head.headers[header] == got.headers[header], header
    assert int(head.headers["content-length"]) == len(got.content)
    # As the GET: credentials first, then the trial; nothing made for either refusal.
    assert api.client.head(url).status_code == 401
    other = api.client.head(f"/api/v1/trials/{measured + 1}/report.pdf", headers=api.headers)
    assert other.status_code == 404
    assert renders == [measured]
