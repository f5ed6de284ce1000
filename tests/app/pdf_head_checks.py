"""What ``HEAD`` on a PDF report must answer, before the PDF is made and after: shared by
the trial report's and the visit report's tests (tests/app/test_report_pdf_head.py,
tests/app/test_visit_report_pdf_head.py).

``renders`` is the list of what the renderer made during the test (the owner's id, each
time it ran); ``exports()`` counts the ``export`` audit events of this report.
"""

from __future__ import annotations

from collections.abc import Callable

from api_support import Api


def head_before_made(
    api: Api, url: str, owner: int, renders: list[int], exports: Callable[[], int]
) -> None:
    """A ``HEAD`` of a report not made yet: its headers, no body, audited, nothing made;
    the ``GET`` after it makes the report."""
    head = api.client.head(url, headers=api.headers)
    assert head.status_code == 200, head.text
    assert renders == []  # not made for a HEAD
    assert head.content == b""
    assert head.headers["content-type"] == "application/pdf"
    # Its length is known only once made: none is sent rather than a wrong one (0).
    assert "content-length" not in head.headers
    assert exports() == 1  # audited as the GET is

    got = api.client.get(url, headers=api.headers)
    assert got.status_code == 200 and got.content.startswith(b"%PDF")
    assert renders == [owner]  # the GET made it: it was not in the cache before
    assert head.headers["content-disposition"] == got.headers["content-disposition"]


def head_after_made(
    api: Api, url: str, owner: int, renders: list[int], exports: Callable[[], int], other_url: str
) -> None:
    """A ``HEAD`` of a report the ``GET`` made: the ``GET``'s headers, no body, audited; as
    the ``GET``, credentials first (401), then the owner (``other_url``: 404), nothing made
    for either refusal."""
    got = api.client.get(url, headers=api.headers)
    assert got.status_code == 200, got.text
    head = api.client.head(url, headers=api.headers)
    assert head.status_code == 200, head.text
    assert renders == [owner]  # made once, by the GET
    assert head.content == b""
    for header in ("content-type", "content-length", "content-disposition"):
        assert head.headers[header] == got.headers[header], header
    assert int(head.headers["content-length"]) == len(got.content)
    assert exports() == 2
    assert api.client.head(url).status_code == 401
    assert api.client.head(other_url, headers=api.headers).status_code == 404
    assert renders == [owner]
