# ruff: noqa: F811  (pytest fixtures imported from api_support and test_pages are parameters)
"""``HEAD`` on the visit report's PDF answers its headers without making the report.

A visit report is made when first asked for (2-3 s of WeasyPrint's CPU for a visit of
several tasks) and kept in the report cache. ``HEAD`` went through the ``GET``'s code and
made it too, only for the server to throw the body away, as a trial's report did before
9b7ddb0 (tests/app/test_report_pdf_head.py).
"""

from __future__ import annotations

import pytest
from api_support import Api, api  # noqa: F401 - fixtures
from pdf_head_checks import head_after_made, head_before_made
from test_pages import client, login, seeded  # noqa: F401 - fixtures
from test_visit_api import _visit

from app.models import Trial
from app.services import visits as visits_service


@pytest.fixture
def visit(api: Api) -> int:
    """A visit's session with measured trials; no visit report made yet."""
    return _visit(api)["session_id"]


@pytest.fixture
def renders(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """The sessions whose visit report is made, in order (the real renderer still runs)."""
    made: list[int] = []
    real = visits_service.render_visit_pdf

    def counted(visit):
        made.append(visit.session_id)
        return real(visit)

    monkeypatch.setattr(visits_service, "render_visit_pdf", counted)
    return made


def _exports(api: Api, session_id: int) -> int:
    return sum(
        1
        for e in api.audit_events()
        if (e.action, e.resource_type, e.resource_id)
        == ("export", "visit_report_pdf", str(session_id))
    )


def test_head_of_a_visit_report_not_made_yet_does_not_make_it(
    api: Api, visit: int, renders: list[int]
) -> None:
    url = f"/api/v1/sessions/{visit}/report.pdf"
    head_before_made(api, url, visit, renders, lambda: _exports(api, visit))


def test_head_of_a_visit_report_made_gives_the_gets_headers(
    api: Api, visit: int, renders: list[int]
) -> None:
    url = f"/api/v1/sessions/{visit}/report.pdf"
    other = "/api/v1/sessions/999999/report.pdf"
    head_after_made(api, url, visit, renders, lambda: _exports(api, visit), other)


def test_head_on_the_pages_visit_report_does_not_make_it(
    client,
    seeded,
    db_sessionmaker,
    renders: list[int],
) -> None:
    """The page's download (``/sessions/{id}/visit-report.pdf``) takes no ``HEAD`` at all
    (405, as every page route): whatever it answers, it must not make the report."""
    login(client)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    head = client.head(f"/sessions/{session_id}/visit-report.pdf")
    assert head.status_code in (200, 405), head.status_code
    assert renders == []
    assert client.get(f"/sessions/{session_id}/visit-report.pdf").status_code == 200
    assert renders == [session_id]  # the counter sees the page's GET
