"""The compare view's plots can be read at the size the page gives them (issue 14, list 5).

Debian's Chromium lays out the trial page with ``?compare=`` at 1280x800 and
768x1024; every text of every compare plot must then be at least
:data:`MIN_TEXT_PX` CSS pixels high as drawn (its font size scaled by the SVG's
drawn width over its own width), and each plot at least :data:`MIN_WIDTH_PX`
wide. 9 px is a common floor for chart labels on screen; the tap numbers
above the aperture peaks (6.5 pt) were drawn at 8.7 px at 768 px wide.

The page comes from the application in this process (a TestClient, logged in);
Chromium's requests are answered by it through Playwright's routing, so no
server is started.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from test_pages import client, login, seeded  # noqa: F401 - fixtures

pytestmark = pytest.mark.browser

CHROMIUM = "/usr/bin/chromium"
ORIGIN = "http://bradyscope.test"
VIEWPORTS = {"desktop": {"width": 1280, "height": 800}, "tablet": {"width": 768, "height": 1024}}
MIN_TEXT_PX = 9.0  # CSS px: the smallest text of a plot as drawn
MIN_WIDTH_PX = 300.0  # CSS px

TEXT_SIZES_JS = """() => Array.from(document.querySelectorAll('[data-compare-plot] svg')).map(svg => {
  const drawn = svg.getBoundingClientRect().width;
  const own = svg.viewBox.baseVal && svg.viewBox.baseVal.width
      ? svg.viewBox.baseVal.width : svg.width.baseVal.value;
  const sizes = Array.from(svg.querySelectorAll('text')).map(t =>
      parseFloat(getComputedStyle(t).fontSize) * drawn / own);
  return {plot: svg.closest('[data-compare-plot]').dataset.comparePlot, drawn: drawn,
          texts: sizes.length, smallest: sizes.length ? Math.min(...sizes) : null};
})"""


@pytest.fixture
def chromium():
    if not Path(CHROMIUM).is_file():
        if os.environ.get("CI"):
            pytest.fail(f"{CHROMIUM} is missing in CI; install Debian's chromium package")
        pytest.skip(f"{CHROMIUM} is not installed (apt-get install chromium)")
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(
            executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
        )
        try:
            yield browser
        finally:
            browser.close()


def _serve_from(client):  # noqa: F811 - the TestClient fixture
    def answer(route, request) -> None:
        path = request.url.removeprefix(ORIGIN)
        response = client.request(request.method, path, content=request.post_data_buffer)
        headers = {
            k: v for k, v in response.headers.items() if k.lower() not in ("content-length",)
        }
        route.fulfill(status=response.status_code, headers=headers, body=response.content)

    return answer


@pytest.mark.parametrize("viewport", sorted(VIEWPORTS))
def test_compare_plots_are_readable_at_their_size(chromium, client, seeded, viewport):  # noqa: F811
    login(client)
    a, b = seeded["trials"][(1, "right")], seeded["trials"][(0, "right")]
    context = chromium.new_context(viewport=VIEWPORTS[viewport])
    try:
        page = context.new_page()
        page.route(f"{ORIGIN}/**", _serve_from(client))
        response = page.goto(f"{ORIGIN}/trials/{a}?compare={b}")
        assert response is not None and response.status == 200
        plots = page.evaluate(TEXT_SIZES_JS)
    finally:
        context.close()
    names = {p["plot"] for p in plots}
    assert names == {"aperture-a", "aperture-b", "amplitude-a", "amplitude-b"}, plots
    for p in plots:
        assert p["texts"] > 3, p  # axis labels and ticks are text (svg.fonttype none)
        assert p["drawn"] >= MIN_WIDTH_PX, (viewport, p)
        assert p["smallest"] >= MIN_TEXT_PX, (viewport, p)
