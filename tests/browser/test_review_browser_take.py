"""The review view of a browser take in Debian's Chromium: the player's time to a frame
through the take's own frame times (``app/static/review.js``).

A take as Chromium's recorder writes it (``tests/browser_takes.py``: WebM stating
1000 fps, 3 ms of capture jitter at 30 fps, the left camera losing a frame after each
of its frames 20, 21, 22 and 50) is uploaded to a real ``bradyscope serve`` and measured
by its worker. Its proxy holds each frame at its capture time; read as ``i / fps`` the
player's time would name a frame up to four frames away after the lost ones. Seeking
the left video to times inside chosen frames, the page must name the frame whose time
span holds that time, draw that frame's tracked markers where the picture shows them,
and playing must run to the take's end.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from browser_support import Recording, log_in
from browser_takes import chromium_take, packet_times_s
from test_browser_flow import VIEWPORTS
from test_review_view import THUMB_DISC_JS, _measured_trial

pytestmark = pytest.mark.browser

# The centroid (video pixels, OpenCV's convention) of the bright pixels of the lead
# video's picture within ``r`` px of ``(x, y)``: where the picture on screen shows the
# marker the overlay draws there.
PICTURE_BLOB_JS = """([side, x, y, r]) => {
  const v = document.querySelector(`video[data-video="${side}"]`);
  const c = document.createElement('canvas');
  c.width = v.videoWidth; c.height = v.videoHeight;
  const ctx = c.getContext('2d');
  ctx.drawImage(v, 0, 0);
  const x0 = Math.max(0, Math.round(x - r)), y0 = Math.max(0, Math.round(y - r));
  const w = Math.min(c.width, Math.round(x + r) + 1) - x0, h = Math.min(c.height, Math.round(y + r) + 1) - y0;
  const img = ctx.getImageData(x0, y0, w, h).data;
  let lo = 255, hi = 0;
  for (let i = 0; i < img.length; i += 4) { lo = Math.min(lo, img[i + 1]); hi = Math.max(hi, img[i + 1]); }
  const cut = (lo + hi) / 2;
  let n = 0, sx = 0, sy = 0;
  for (let i = 0; i < img.length; i += 4) {
    if (img[i + 1] > cut) { const p = i / 4; sx += x0 + (p % w); sy += y0 + Math.floor(p / w); n++; }
  }
  return n ? {x: sx / n, y: sy / n, n: n, contrast: hi - lo} : null;
}"""

# The frame the page names is cleared first, so that the one read after is the seek's.
SEEK_JS = """(t) => {
  const v = document.querySelector('video[data-video=left]');
  v.pause();
  document.querySelector('[data-review-player]').dataset.frame = 'seeking';
  v.currentTime = t;
}"""

SETTLED_JS = """() => {
  const player = document.querySelector('[data-review-player]');
  return player.dataset.frame !== 'seeking'
    && [...document.querySelectorAll('video')].every((v) => !v.seeking && v.readyState >= 2);
}"""


@pytest.fixture(scope="module")
def browser_take(simulated_session, tmp_path_factory):
    return chromium_take(simulated_session, tmp_path_factory.mktemp("chromium"))


def test_review_of_a_browser_take_follows_its_frame_times(
    browser, served, browser_take, screenshot_dir
):
    sim, videos = browser_take
    context = browser.new_context(viewport=VIEWPORTS["desktop"])
    page = context.new_page()
    page.set_default_timeout(30_000)
    page.goto(f"{served.url}/login")
    csrf = log_in(page, served)
    take = Recording(videos["left"], videos["right"], sim.rig_path, sim.truth)
    trial_id = _measured_trial(page, served, take, csrf, tag="webm")

    page.goto(f"{served.url}/trials/{trial_id}/review")
    data = json.loads(page.locator("#review-data").text_content())
    page.wait_for_function(
        "() => [...document.querySelectorAll('video')].every(v => v.readyState >= 2)"
    )
    cam = next(c for c in data["overlay"]["cameras"] if c["video"] == "left")
    assert cam["camera"] == "left"  # the left video leads
    times = np.asarray(cam["time_s"])
    np.testing.assert_allclose(times, packet_times_s(videos["left"]), atol=1e-6)  # s
    period = float(np.median(np.diff(times)))  # s
    n = len(times)
    assert n == cam["frame_count"] and np.sum(np.diff(times) > 1.5 * period) >= 2  # gaps

    # Inside frames before, between and after the lost ones, and at irregular intervals.
    late = np.argsort(np.diff(times))[-8:]  # the frames before the longest intervals
    frames = sorted({3, 19, 21, 22, 23, 30, 51, 52, 60, n - 3, *late.tolist(), *(late + 1)})
    frames = [int(k) for k in frames if 0 <= k < n - 1]
    misread = 0
    for k in frames:
        for share in (0.2, 0.8):
            t = float(times[k] + share * (times[k + 1] - times[k]))
            misread += int(np.floor(t * data["fps"] + 0.001)) != k  # i / fps's frame
            page.evaluate(SEEK_JS, t)
            page.wait_for_function(SETTLED_JS)
            shown = int(page.locator("[data-review-player]").get_attribute("data-frame"))
            # The frame named is the one at that time: its time within half a period before.
            assert times[shown] <= t + 1e-4 and t - times[shown] < max(
                0.5 * period, times[shown + 1] - times[shown]
            ), (k, share, shown)
            assert shown == k
            drawn = int(page.locator("video[data-video=left]").get_attribute("data-frame"))
            assert drawn == k
            # The overlay's thumb at the frame's tracked position ...
            disc = page.evaluate(THUMB_DISC_JS, "left")
            thumb = cam["tracks"]["thumb"][k]
            if thumb is None:
                continue
            assert disc is not None and disc["n"] > 50, (k, disc)
            assert abs(disc["x"] - thumb[0]) < 0.5 and abs(disc["y"] - thumb[1]) < 0.5  # px
            # ... where the picture on screen shows the marker.
            blob = page.evaluate(PICTURE_BLOB_JS, ["left", thumb[0], thumb[1], 8])
            assert blob is not None and blob["contrast"] > 40, (k, blob)
            assert np.hypot(blob["x"] - thumb[0], blob["y"] - thumb[1]) < 2.0, (k, blob)  # px
    assert misread >= 10  # i / fps would have named other frames than these
    page.screenshot(path=str(screenshot_dir / "review-browser-take.png"), full_page=True)

    # Playing runs to the take's end: the proxy lasts as long as the take.
    duration = page.evaluate("() => document.querySelector('video[data-video=left]').duration")
    assert abs(duration - (times[-1] + period)) <= period, duration  # s
    page.evaluate(SEEK_JS, float(times[-1] - 1.0))
    page.wait_for_function(SETTLED_JS)
    page.click("[data-action=play]")
    page.wait_for_function(
        "() => document.querySelector('video[data-video=left]').ended", timeout=60_000
    )
    end = page.evaluate("() => document.querySelector('video[data-video=left]').currentTime")
    assert abs(end - duration) <= period  # s
    last = int(page.locator("[data-review-player]").get_attribute("data-frame"))
    assert last >= n - 2, (last, n)
    context.close()
