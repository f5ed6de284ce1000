# ruff: noqa: F811  (pytest fixtures imported from api_support are parameters here)
"""Downloads a client can check cheaply: ``If-None-Match`` answers 304, ``HEAD`` the headers.

markers.csv sent an ETag but ignored ``If-None-Match`` (the whole file again), and
``HEAD`` on a download was 405.
"""

from __future__ import annotations

import pytest
from api_support import Api, api, video_pair  # noqa: F401 - fixtures
from test_revisions import _trial


@pytest.fixture
def measured(api: Api, video_pair) -> int:
    return _trial(api, video_pair)


def test_markers_csv_answers_304_to_its_etag(api: Api, measured: int) -> None:
    url = f"/api/v1/trials/{measured}/markers.csv"
    first = api.client.get(url, headers=api.headers)
    assert first.status_code == 200 and first.content
    etag = first.headers["etag"]
    for sent in (etag, f"W/{etag}", f'"other", {etag}', "*"):
        again = api.client.get(url, headers={**api.headers, "If-None-Match": sent})
        assert again.status_code == 304, sent
        assert again.content == b"" and again.headers["etag"] == etag
    other = api.client.get(url, headers={**api.headers, "If-None-Match": '"older"'})
    assert other.status_code == 200 and other.content == first.content
    # A new revision is another file: another ETag, so the client's copy is not current.
    swap = api.client.post(
        f"/api/v1/trials/{measured}/revisions",
        json={"swap_labels": True, "reason": "thumb and index the wrong way round"},
        headers=api.headers,
    )
    assert swap.status_code == 201, swap.text
    newer = api.client.get(url, headers={**api.headers, "If-None-Match": etag})
    assert newer.status_code == 200 and newer.headers["etag"] != etag
    assert api.client.get(f"{url}?revision=1", headers=api.headers).headers["etag"] == etag


@pytest.mark.parametrize("name", ["markers.csv", "markers.c3d", "markers.trc"])
def test_head_of_a_download_gives_its_headers(api: Api, measured: int, name: str) -> None:
    url = f"/api/v1/trials/{measured}/{name}"
    got = api.client.get(url, headers=api.headers)
    head = api.client.head(url, headers=api.headers)
    assert head.status_code == 200, head.text
    assert head.content == b""
    for header in ("content-type", "content-length", "content-disposition"):
        assert head.headers[header] == got.headers[header], header
    assert api.client.head(url).status_code == 401  # as the GET: credentials first
    assert (
        api.client.head(f"/api/v1/trials/{measured + 1}/{name}", headers=api.headers).status_code
        == 404
    )
