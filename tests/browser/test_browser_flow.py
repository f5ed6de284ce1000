"""The clinician's whole path in Debian's Chromium, against a real ``bradyscope serve``.

Log in (keyboard only), add a rig and upload its rig file, add a patient, start
a session, upload a simulated recording with the progress bar, watch the job
finish, open the result page (every plot present and drawn), compare nothing
is broken at 1280x800 and 768x1024 (screenshots), download the PDF and check
its text. The test fails on any error page, console error or CSP violation,
unlabelled form field, missing or empty plot.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

pytestmark = pytest.mark.browser

PLOTS = ("aperture", "amplitude", "velocity", "paths")
VIEWPORTS = {"desktop": {"width": 1280, "height": 800}, "tablet": {"width": 768, "height": 1024}}

UNLABELLED_JS = """() => Array.from(document.querySelectorAll(
    'input:not([type=hidden]), select, textarea'))
  .filter(el => !(el.labels && el.labels.length) && !el.getAttribute('aria-label'))
  .map(el => el.name || el.id || el.outerHTML.slice(0, 60))"""

PLOT_JS = """(name) => {
  const svg = document.querySelector(`svg[data-plot="${name}"]`);
  if (!svg) return null;
  const box = svg.getBoundingClientRect();
  return {width: box.width, height: box.height,
          paths: svg.querySelectorAll('path').length,
          title: (svg.querySelector('title') || {}).textContent || ''};
}"""

WATCH_PROGRESS_JS = """() => {
  sessionStorage.setItem('bs-progress', '[]');
  document.querySelectorAll('form[data-upload] progress').forEach(bar => {
    new MutationObserver(() => {
      const seen = JSON.parse(sessionStorage.getItem('bs-progress') || '[]');
      seen.push(Number(bar.value));
      sessionStorage.setItem('bs-progress', JSON.stringify(seen));
    }).observe(bar, {attributes: true, attributeFilter: ['value']});
  });
}"""


class PageChecker:
    """Collects console errors and checks every page for errors and labels."""

    def __init__(self, page):
        self.page = page
        self.problems: list[str] = []
        page.on(
            "console", lambda m: m.type == "error" and self.problems.append(f"console: {m.text}")
        )
        page.on("pageerror", lambda e: self.problems.append(f"page error: {e}"))

    def check(self, what: str) -> None:
        page = self.page
        title = page.title()
        assert not re.match(r"(Not found|Not allowed|Something went wrong|Not ready)", title), (
            what,
            title,
        )
        alerts = [
            a
            for a in page.locator("[role=alert]").all()
            if a.is_visible() and a.inner_text().strip()
        ]
        assert not alerts, (what, [a.inner_text() for a in alerts])
        assert page.evaluate(UNLABELLED_JS) == [], f"{what}: form fields without a label"
        assert not self.problems, (what, self.problems)

    def goto(self, url: str, what: str):
        response = self.page.goto(url)
        assert response is not None and response.status < 400, (what, response and response.status)
        self.check(what)


def _tab_to(page, selector: str, max_tabs: int = 40) -> bool:
    target = page.locator(selector)
    for _ in range(max_tabs):
        page.keyboard.press("Tab")
        if target.evaluate("el => el === document.activeElement"):
            return True
    return False


def _shots(page, name: str, directory: Path) -> None:
    for label, size in VIEWPORTS.items():
        page.set_viewport_size(size)
        overflow = page.evaluate("() => document.documentElement.scrollWidth - window.innerWidth")
        assert overflow <= 1, f"{name} at {label}: the page is {overflow} px wider than the screen"
        page.screenshot(path=str(directory / f"{name}-{label}.png"), full_page=True)
    page.set_viewport_size(VIEWPORTS["desktop"])


def test_clinician_flow(browser, served, recording, screenshot_dir, tmp_path):
    email, password = served.email, served.password
    context = browser.new_context(viewport=VIEWPORTS["desktop"], accept_downloads=True)
    page = context.new_page()
    page.set_default_timeout(30_000)
    pages = PageChecker(page)

    # 1. Every page needs a login; log in with the keyboard only.
    pages.goto(f"{served.url}/patients", "login redirect")
    assert "/login" in page.url
    _shots(page, "login", screenshot_dir)
    assert page.evaluate("() => document.activeElement.id") == "email"  # autofocus
    page.keyboard.type(email)
    page.keyboard.press("Tab")
    page.keyboard.type(password)
    page.keyboard.press("Enter")
    page.wait_for_url(re.compile(r"/patients$"))
    pages.check("patient list")

    # 2. A rig and its calibration from the recording's rig file.
    pages.goto(f"{served.url}/rigs", "rigs")
    page.fill("#rig-name", "browser-rig")
    page.click("text=Add rig")
    page.wait_for_url(re.compile(r"/rigs/\d+"))
    pages.check("new rig")
    page.set_input_files("#rig-json", str(recording.rig))
    page.click("text=Upload rig file")
    page.wait_for_selector("text=Version 1")
    pages.check("rig with calibration")
    assert page.locator(".verdict").first.inner_text().strip().lower() in (
        "good",
        "acceptable",
        "poor",
    )
    _shots(page, "rig", screenshot_dir)

    # 3. A patient and a session, the form reached with the keyboard.
    pages.goto(f"{served.url}/patients", "patient list")
    assert _tab_to(page, "#code"), "the patient code field cannot be reached with Tab"
    page.keyboard.type("PD-7777")
    page.keyboard.press("Enter")
    page.wait_for_url(re.compile(r"/patients/\d+"))
    pages.check("patient page")
    page.click("text=New session")
    page.wait_for_url(re.compile(r"/sessions/new"))
    pages.check("new session form")
    page.select_option("#rig_id", label="browser-rig")
    page.check("input[name=medication_state][value=off]")
    page.fill("#time_since_levodopa_min", "720")
    page.check("input[name=more_affected_side][value=right]")
    page.click("text=Create session")
    page.wait_for_url(re.compile(r"/sessions/\d+"))
    pages.check("session page")
    _shots(page, "session", screenshot_dir)

    # 4. Upload the right hand through the script (XHR with progress) and follow the job.
    uploads = []
    page.on(
        "request",
        lambda r: r.method == "POST" and r.url.endswith("/trials") and uploads.append(r),
    )
    page.evaluate(WATCH_PROGRESS_JS)
    page.set_input_files("#left-video-right", str(recording.left))
    page.set_input_files("#right-video-right", str(recording.right))
    page.click("text=Upload and measure the right hand")
    page.wait_for_url(re.compile(r"/jobs/\d+"), timeout=60_000)
    pages.check("job page")
    assert len(uploads) == 1 and uploads[0].resource_type == "xhr"
    assert uploads[0].headers.get("x-csrf-token")
    progress = page.evaluate("() => JSON.parse(sessionStorage.getItem('bs-progress') || '[]')")
    assert progress and max(progress) == 100, f"the upload progress bar did not move: {progress}"
    page.wait_for_function(
        "() => ['succeeded', 'failed'].includes(document.querySelector('[data-job-status]').textContent.trim())",
        timeout=150_000,
    )
    status = page.locator("[data-job-status]").inner_text().strip()
    assert status == "succeeded", page.locator("[data-job-error-text]").inner_text()
    assert page.locator("[data-job-progress]").get_attribute("value") == "100"
    _shots(page, "job", screenshot_dir)

    # 5. The result page: every plot present and drawn, metrics and quality shown.
    page.click("[data-job-result]")
    page.wait_for_url(re.compile(r"/trials/\d+"))
    pages.check("result page")
    for name in PLOTS:
        info = page.evaluate(PLOT_JS, name)
        assert info is not None, f"the {name} plot is missing"
        assert info["width"] > 200 and info["height"] > 80, (name, info)
        assert info["paths"] > 10, (name, info)
        assert not re.search(r"no data|no taps", info["title"], re.I), (name, info["title"])
    values = {
        row.get_attribute("data-metric"): row.locator("td.num").first.inner_text().strip()
        for row in page.locator("table.metrics tbody tr[data-metric]").all()
    }
    assert values.get("tap_count") not in (None, "–", "0"), values
    assert page.locator("text=Measurement quality").count() == 1
    assert page.locator("text=Calibration used").count() == 1
    # The summary block (first 10 taps, four aspects with their bands) is in the first screen.
    page.evaluate("() => window.scrollTo(0, 0)")
    box = page.locator("table[data-summary]").bounding_box()
    assert box is not None and box["y"] + box["height"] <= VIEWPORTS["desktop"]["height"], box
    assert page.locator("table[data-summary] [data-band]").count() >= 4
    _shots(page, "result", screenshot_dir)
    trial_url = page.url

    # 5b. The clinician's own rating of this hand, saved on the trial.
    page.select_option("#clinician_rating", "2")
    page.fill("#rating_comment", "Slows after tap 6.")
    page.click("text=Save rating")
    page.wait_for_url(re.compile(r"/trials/\d+"))
    pages.check("rated trial")
    assert page.locator("#clinician_rating").input_value() == "2"
    # A bad comparison id answers with the page and a message, not raw JSON.
    response = page.goto(f"{trial_url}?compare=abc")
    assert response is not None and response.status == 200
    assert "is not a trial number" in page.locator("#compare").inner_text()
    page.goto(trial_url)

    # 6. The patient's page now shows the trend plots.
    page.click("nav.crumbs >> text=PD-7777")
    page.wait_for_url(re.compile(r"/patients/\d+$"))
    pages.check("patient page with result")
    # One visit: a table of its first-10-tap values, not five one-dot plots.
    assert page.locator("[data-trend-table]").count() == 1
    assert page.locator("svg[data-plot=trend]").count() == 0
    _shots(page, "patient", screenshot_dir)
    page.go_back()
    page.wait_for_url(re.compile(r"/trials/\d+$"))

    # 7. Download the PDF report and read it.
    with page.expect_download() as info:
        page.click("a[data-download=pdf]")
    pdf = tmp_path / "report.pdf"
    info.value.save_as(pdf)
    assert pdf.read_bytes().startswith(b"%PDF")
    if shutil.which("pdftotext"):
        text = subprocess.run(
            ["pdftotext", "-layout", str(pdf), "-"], capture_output=True, text=True, check=True
        ).stdout
        assert "PD-7777" in text
        for key in ("tap_count", "frequency_hz", "amplitude_mm_mean"):
            assert values[key] in text, (key, values[key])
    pages.check("after download")

    # 8. The visit report from the session page: page 1 summarises the visit.
    page.click("nav.crumbs >> text=Session")
    page.wait_for_url(re.compile(r"/sessions/\d+$"))
    session_url = page.url
    with page.expect_download() as info:
        page.click("a[data-visit-report]")
    visit_pdf = tmp_path / "visit.pdf"
    info.value.save_as(visit_pdf)
    if shutil.which("pdftotext"):
        page1 = subprocess.run(
            ["pdftotext", "-f", "1", "-l", "1", str(visit_pdf), "-"],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        page1 = " ".join(page1.split())
        assert "Right hand, medication off" in page1
        assert values["frequency_hz"] in page1 or "Tapping frequency" in page1
        assert "Slows after tap 6." in page1 and "bradyscope" in page1
    pages.goto(f"{session_url}/visit-report.html", "visit report")
    _shots(page, "visit-report", screenshot_dir)
    context.close()
    print(f"\nscreenshots in {screenshot_dir}")
