"""The review view in Debian's Chromium, against a real ``bradyscope serve`` and worker.

A simulated recording is measured by the worker; its review view plays the
browser proxies, draws the tracked markers where the detector found them
(read back from the canvas pixels and compared with the overlay data), moves
the aperture cursor with the video, jumps to a clicked tap; a tap excluded
from the page with a reason gives the metrics core computes without it, and
revision 1 is still served unchanged.
"""

from __future__ import annotations

import io
import json
import re
import time

import pytest
from browser_support import Recording, log_in
from test_browser_flow import VIEWPORTS, PageChecker

from core.cycles import common_metrics
from core.markers_csv import MEASURED, read_markers_csv
from core.metrics import compute_metrics, tapping_metrics

pytestmark = pytest.mark.browser

# Centroid of the thumb's disc (exact fill colour, so antialiased edges and the labels
# do not count), in OpenCV pixels: a canvas pixel i covers [i, i + 1) and the script
# draws a point x at x + 0.5, so the mean pixel index is x itself.
# Each overlay drawn by the script that has just asked its video to seek (so before the
# new frame can be on screen) is logged: the player must draw it once the seek lands.
DRAWN_AHEAD_OF_SEEK_JS = """() => {
  window.drawnAheadOfSeek = [];
  const time = Object.getOwnPropertyDescriptor(HTMLMediaElement.prototype, 'currentTime');
  document.querySelectorAll('video[data-video]').forEach((v) => {
    let seekAsked = false;  // by the script now running: cleared once it has run
    Object.defineProperty(v, 'currentTime', {
      configurable: true,
      get() { return time.get.call(v); },
      set(t) { seekAsked = true; queueMicrotask(() => { seekAsked = false; }); time.set.call(v, t); },
    });
    const setAttribute = v.setAttribute.bind(v);
    v.setAttribute = (name, value) => {
      if (name === 'data-frame' && seekAsked) window.drawnAheadOfSeek.push([v.dataset.video, value]);
      setAttribute(name, value);
    };
  });
}"""

THUMB_DISC_JS = """(side) => {
  const c = document.querySelector(`canvas[data-overlay="${side}"]`);
  const img = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
  const hex = JSON.parse(document.getElementById('review-data').textContent).marker_colours.thumb;
  const [r, g, b] = [1, 3, 5].map((k) => parseInt(hex.slice(k, k + 2), 16));
  let n = 0, sx = 0, sy = 0;
  for (let i = 0; i < img.length; i += 4) {
    if (img[i] === r && img[i + 1] === g && img[i + 2] === b && img[i + 3] === 255) {
      const p = i / 4; sx += p % c.width; sy += Math.floor(p / c.width); n++;
    }
  }
  return n ? {x: sx / n, y: sy / n, n: n} : null;
}"""


def _api(page, method: str, url: str, csrf: str, **kw):
    r = page.request.fetch(url, method=method, headers={"X-CSRF-Token": csrf}, **kw)
    assert r.ok, (url, r.status, r.text()[:300])
    return r


def _measured_trial(page, served, recording, csrf: str, *, tag: str = "review") -> int:
    base = f"{served.url}/api/v1"
    rig = _api(page, "POST", f"{base}/rigs", csrf, data={"name": f"{tag}-rig"}).json()
    _api(
        page,
        "POST",
        f"{base}/rigs/{rig['id']}/calibrations",
        csrf,
        multipart={
            "rig_json": {
                "name": "rig.json",
                "mimeType": "application/json",
                "buffer": recording.rig.read_bytes(),
            }
        },
    )
    patient = _api(
        page, "POST", f"{base}/patients", csrf, data={"code": f"PD-{tag.upper()}"}
    ).json()
    session = _api(
        page,
        "POST",
        f"{base}/sessions",
        csrf,
        data={
            "patient_id": patient["id"],
            "rig_id": rig["id"],
            "recorded_at": "2026-05-01T10:00:00Z",
            "medication_state": "off",
        },
    ).json()
    # The videos go up through the session page's form (streamed from the files).
    page.goto(f"{served.url}/sessions/{session['id']}")
    page.set_input_files("#left-video-right", str(recording.left))
    page.set_input_files("#right-video-right", str(recording.right))
    page.click("text=Upload and measure the right hand")
    page.wait_for_url(re.compile(r"/jobs/\d+"), timeout=120_000)
    job_id = int(page.url.rstrip("/").split("/")[-1])
    trial = {"job_id": job_id}
    deadline = time.monotonic() + 240
    while True:
        job = page.request.get(f"{base}/jobs/{trial['job_id']}").json()
        if job["status"] in ("succeeded", "failed"):
            break
        assert time.monotonic() < deadline, job
        time.sleep(0.5)  # polling the worker, not timing a measurement
    assert job["status"] == "succeeded", job["error"]
    return int(job["trial_id"])


def test_review_view(browser, served, recording, screenshot_dir):
    context = browser.new_context(viewport=VIEWPORTS["desktop"])
    page = context.new_page()
    page.set_default_timeout(30_000)
    pages = PageChecker(page)
    pages.goto(f"{served.url}/login", "login")
    csrf = log_in(page, served)
    trial_id = _measured_trial(page, served, recording, csrf)
    original = page.request.get(f"{served.url}/api/v1/trials/{trial_id}/result").json()

    pages.goto(f"{served.url}/trials/{trial_id}/review", "review view")
    data = json.loads(page.locator("#review-data").text_content())
    fps = data["fps"]
    page.wait_for_function(
        "() => [...document.querySelectorAll('video')].every(v => v.readyState >= 2)"
    )

    # The videos play, and the aperture cursor follows the video time.
    page.click("[data-action=play]")
    page.wait_for_function(
        "() => document.querySelector('video[data-video=left]').currentTime > 0.4"
    )
    gaps = []
    for _ in range(5):
        t, cursor = page.evaluate(
            """() => [document.querySelector('video[data-video=left]').currentTime,
                      parseFloat(document.querySelector('canvas[data-aperture]').dataset.cursorS)]"""
        )
        gaps.append(abs(t - cursor))
        page.wait_for_timeout(80)
    assert max(gaps) < 0.1, gaps  # s: within a few frames while playing
    live = "() => document.querySelector('.review-position').getAttribute('aria-live')"
    assert page.evaluate(live) == "off"  # not announced 100 times a second
    page.click("[data-action=play]")  # pause
    assert page.evaluate(live) == "polite"  # stepping and jumping are announced

    # Step to the peak of a tap (markers far apart) with the keyboard and read the drawing back.
    tap = data["taps"][2]
    frame = round(tap["t_max_aperture_s"] * fps)
    page.evaluate(DRAWN_AHEAD_OF_SEEK_JS)
    page.evaluate("(f) => window.bradyscopeReview.seekFrame(f - 3)", frame)
    page.wait_for_function(
        f"() => document.querySelector('[data-review-player]').dataset.frame === '{frame - 3}'"
    )
    page.locator("main h1").click()  # focus outside the form fields
    for _ in range(3):
        page.keyboard.press("ArrowRight")
    page.wait_for_function(
        f"() => document.querySelector('[data-review-player]').dataset.frame === '{frame}'"
    )
    cursor = float(page.locator("canvas[data-aperture]").get_attribute("data-cursor-s"))
    assert cursor == pytest.approx(frame / fps, abs=1e-3)
    page.wait_for_function(
        "() => [...document.querySelectorAll('video')].every(v => !v.seeking && v.readyState >= 2)"
    )
    # Each overlay was drawn with its own video's frame on screen, never ahead of it.
    assert page.evaluate("() => window.drawnAheadOfSeek") == []
    for cam in data["overlay"]["cameras"]:
        side = cam["video"]
        own = int(page.locator(f"video[data-video={side}]").get_attribute("data-frame"))
        drawn = page.evaluate(THUMB_DISC_JS, side)
        assert drawn is not None and drawn["n"] > 50, (side, drawn)
        tracked = cam["tracks"]["thumb"][own]
        nearest = min(
            cam["detections"][own],
            key=lambda d: (d[0] - drawn["x"]) ** 2 + (d[1] - drawn["y"]) ** 2,
        )
        assert abs(drawn["x"] - tracked[0]) < 0.5 and abs(drawn["y"] - tracked[1]) < 0.5, side
        assert abs(drawn["x"] - nearest[0]) < 1 and abs(drawn["y"] - nearest[1]) < 1, side  # px
    page.screenshot(path=str(screenshot_dir / "review-desktop.png"), full_page=True)

    # Jump to a tap by clicking it in the list.
    jump = data["taps"][5]
    page.click(f"[data-tap-row='{jump['index']}'] button[data-jump]")
    target = str(round(jump["t_start_s"] * fps))
    page.wait_for_function(
        f"() => document.querySelector('[data-review-player]').dataset.frame === '{target}'"
    )

    # Exclude tap 3 (index 2) with a reason: a new revision with core's metrics without it.
    page.check(f"#ex-{tap['index']}")
    page.fill("#reason", "tap 3 was the patient scratching the thumb")
    page.click("text=Store as a new revision")
    page.wait_for_url(re.compile(rf"/trials/{trial_id}/review"))
    pages.check("review after the correction")
    assert "revision 2 (current)" in page.locator("[data-revision-pill]").inner_text()
    current = page.request.get(f"{served.url}/api/v1/trials/{trial_id}/result").json()
    csv = page.request.get(f"{served.url}/api/v1/trials/{trial_id}/markers.csv").text()
    table = read_markers_csv(io.StringIO(csv), fps=fps)
    full = compute_metrics(table.positions_mm, table.fps, measured=table.status == MEASURED)
    kept = [t for t in full.taps if t.index != tap["index"]]
    events = [e for e in full.events if e["kind"] == "gap" or e["tap_index"] != tap["index"]]
    assert current["revision"] == 2
    expected = tapping_metrics(kept, events)
    expected = {**expected, **common_metrics(expected, "mm")}  # with every task's common keys
    assert current["metrics"] == pytest.approx(expected, abs=1e-12)
    assert current["metrics"]["tap_count"] == original["metrics"]["tap_count"] - 1
    first = page.request.get(f"{served.url}/api/v1/trials/{trial_id}/result?revision=1").json()
    assert first == original
    context.close()


@pytest.fixture(scope="module")
def wide_recording(tmp_path_factory: pytest.TempPathFactory) -> Recording:
    """A 1280x1024 recording: its browser proxies are reduced to 640x512. MPEG-4 (the lab
    rig's), not the simulator's lossless FFV1, which takes several times the CPU to write
    and read and changes nothing the test looks at."""
    from core.camera import ImageSize
    from core.simulation.kinematics import TappingScenario
    from core.simulation.session import ImagingScenario, simulate_session

    sim = simulate_session(
        tmp_path_factory.mktemp("wide-recording"),
        seed=8,
        tapping=TappingScenario(duration_s=2.0, amplitude_mm=45.0, frequency_hz=3.0),
        imaging=ImagingScenario(image_size=ImageSize(1280, 1024), codec="mp4v"),
    )
    return Recording(sim.left_video, sim.right_video, sim.rig_path, sim.truth)


# The video's current frame drawn at its own size: the centroid of its bright pixels
# (> 100) within 7 px of (x, y), in the video's pixels (OpenCV's convention), and their count.
VIDEO_SPOT_JS = """([side, x, y]) => {
  const v = document.querySelector(`video[data-video="${side}"]`);
  const c = document.createElement('canvas');
  c.width = v.videoWidth; c.height = v.videoHeight;
  const ctx = c.getContext('2d');
  ctx.drawImage(v, 0, 0);
  const x0 = Math.round(x) - 7, y0 = Math.round(y) - 7;
  const img = ctx.getImageData(x0, y0, 15, 15).data;
  let n = 0, sx = 0, sy = 0;
  for (let i = 0; i < img.length; i += 4) {
    if (img[i] > 100) { const p = i / 4; sx += x0 + p % 15; sy += y0 + Math.floor(p / 15); n++; }
  }
  return n ? {x: sx / n, y: sy / n, n: n} : null;
}"""

BOXES_JS = """(side) => {
  const v = document.querySelector(`video[data-video="${side}"]`);
  const c = document.querySelector(`canvas[data-overlay="${side}"]`);
  const a = v.getBoundingClientRect(), b = c.getBoundingClientRect();
  return {video: [v.videoWidth, v.videoHeight], canvas: [c.width, c.height],
          video_box: [a.x, a.y, a.width, a.height], canvas_box: [b.x, b.y, b.width, b.height]};
}"""


def test_review_view_draws_on_a_reduced_proxy(browser, served, wide_recording):
    """A 1280x1024 recording plays from 640x512 proxies (core.video.proxy_size): the
    overlay, drawn in the original's pixels, covers the video's box exactly, and the
    thumb's disc lands on the thumb marker's bright spot in the reduced video."""
    context = browser.new_context(viewport=VIEWPORTS["desktop"])
    page = context.new_page()
    page.set_default_timeout(30_000)
    page.goto(f"{served.url}/login")
    csrf = log_in(page, served)
    trial_id = _measured_trial(page, served, wide_recording, csrf, tag="wide")
    page.goto(f"{served.url}/trials/{trial_id}/review")
    data = json.loads(page.locator("#review-data").text_content())
    page.wait_for_function(
        "() => [...document.querySelectorAll('video')].every(v => v.readyState >= 2)"
    )
    frame = round(data["taps"][1]["t_max_aperture_s"] * data["fps"])
    page.evaluate("(f) => window.bradyscopeReview.seekFrame(f)", frame)
    page.wait_for_function(
        f"() => document.querySelector('[data-review-player]').dataset.frame === '{frame}'"
    )
    # The player follows the left video's seek; the right video seeks after it, and shows
    # its frame (read back below) once that seek has landed.
    page.wait_for_function(
        "() => [...document.querySelectorAll('video')].every(v => !v.seeking && v.readyState >= 2)"
    )
    for cam in data["overlay"]["cameras"]:
        side = cam["video"]
        boxes = page.evaluate(BOXES_JS, side)
        assert boxes["video"] == [640, 512] and boxes["canvas"] == [1280, 1024], boxes
        assert boxes["canvas_box"] == pytest.approx(boxes["video_box"], abs=0.5)  # CSS px
        drawn = page.evaluate(THUMB_DISC_JS, side)
        assert drawn is not None and drawn["n"] > 50, (side, drawn)
        # Proxy pixel u averages original pixels 2u and 2u + 1: centre x = 2u + 0.5.
        at = [(drawn["x"] - 0.5) / 2, (drawn["y"] - 0.5) / 2]
        spot = page.evaluate(VIDEO_SPOT_JS, [side, *at])
        assert spot is not None and spot["n"] >= 4, (side, spot)
        assert spot["x"] == pytest.approx(at[0], abs=1.0), (side, spot, at)  # proxy px
        assert spot["y"] == pytest.approx(at[1], abs=1.0), (side, spot, at)  # proxy px
    context.close()
