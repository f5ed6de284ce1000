# ruff: noqa: F811  (pytest fixtures imported from api_support / test_pages are parameters here)
"""A result of each task other than finger tapping: its plots, reports and corrections.

The trials are simulated (``sample_trial.task_trial``: the simulator's
trajectories, measured by core) and stored as the worker stores them. Each
one's result page must draw its own quantity in its own unit with its cycles
marked (the SVG's text is checked), its reports must give its metrics with
units, and a correction must be measured again by the analysis's own code and
match the simulator's truth within the tolerances of the tasks' acceptance
(tests/core/test_task_metrics.py).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess

import numpy as np
import pytest
from api_support import Api, api  # noqa: F401 - fixture
from sample_trial import task_trial
from sqlalchemy import select
from test_pages import client, login, seeded  # noqa: F401 - fixtures

from app.models import Job, RecordingSession, Result, Trial
from core.markers_csv import markers_csv_text
from core.tasks import Task, task_key

NEW_TASKS = (Task.HAND_MOVEMENTS, Task.PRONATION_SUPINATION, Task.TOE_TAPPING, Task.LEG_AGILITY)
# What each task's plots must say: (signal axis label, unit, the two halves of a cycle), and
# the signal in the plot's title and the page's heading.
EXPECTED = {
    Task.HAND_MOVEMENTS: ("finger–wrist distance", "mm", ("opening", "closing")),
    Task.PRONATION_SUPINATION: ("hand rotation angle", "deg", ("supination", "pronation")),
    Task.TOE_TAPPING: ("toe lift", "mm", ("lift", "lowering")),
    Task.LEG_AGILITY: ("thigh rise angle", "deg", ("lift", "lowering")),
}
TITLE = {
    Task.HAND_MOVEMENTS: "Finger–wrist distance",
    Task.PRONATION_SUPINATION: "Rotation of the hand about the forearm",
    Task.TOE_TAPPING: "Toe lift",
    Task.LEG_AGILITY: "Rise of the thigh about the hip",
}
DURATION_S = {
    Task.HAND_MOVEMENTS: 9.0,
    Task.PRONATION_SUPINATION: 11.0,
    Task.TOE_TAPPING: 6.0,
    Task.LEG_AGILITY: 9.0,
}


def store_task_trial(
    db_sessionmaker, storage, task: Task, *, hand: str = "right", session_index: int = -1,
    seed: int = 3, amplitude_scale: float = 1.0,
):  # fmt: skip
    """A trial of ``task`` with a simulated, core-measured result, stored as the worker
    stores it in a session of ``seeded``'s patient; returns (trial id, result.json, truth)."""
    markers, document, truth = task_trial(
        task.value, side=hand, duration_s=DURATION_S[task], seed=seed,
        amplitude_scale=amplitude_scale,
    )  # fmt: skip
    stored = storage.write_bytes("results", ".csv", markers_csv_text(markers).encode())
    with db_sessionmaker() as db:
        session = db.scalars(select(RecordingSession).order_by(RecordingSession.recorded_at)).all()[
            session_index
        ]
        trial = Trial(session_id=session.id, hand=hand, task=task.value, status="succeeded")
        db.add(trial)
        db.flush()
        job = Job(kind="analyze_trial", trial_id=trial.id, status="succeeded", progress=1.0)
        db.add(job)
        db.flush()
        db.add(
            Result(
                trial_id=trial.id, job_id=job.id, document=document, markers_path=stored.path
            )
        )  # fmt: skip
        db.commit()
        return trial.id, document, truth


def _plot(html: str, name: str) -> str:
    match = re.search(rf'<svg[^>]*data-plot="{name}".*?</svg>', html, re.S)
    assert match, f"no {name} plot"
    return match.group(0)


def _texts(svg: str) -> list[str]:
    """The words drawn in an SVG (matplotlib keeps text as text)."""
    return [t.strip() for t in re.findall(r"<text[^>]*>([^<]*)</text>", svg)]


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
@pytest.mark.parametrize("where", ["page", "report"])
def test_the_result_page_plots_the_task_s_own_quantity(
    api: Api, client, seeded, db_sessionmaker, storage, task: Task, where: str
) -> None:
    trial_id, doc, truth = store_task_trial(db_sessionmaker, storage, task)
    signal, unit, (towards, back) = EXPECTED[task]
    if where == "page":
        login(client)
        html = client.get(f"/trials/{trial_id}").text
    else:
        html = api.client.get(f"/api/v1/trials/{trial_id}/report.html", headers=api.headers).text
    n = doc["metrics"]["cycle_count"]
    assert n == len(truth.cycles)

    aperture = _plot(html, "aperture")
    assert f"{signal} ({unit})" in _texts(aperture)  # the y axis
    title = f"{TITLE[task]} over time: {n} cycles, 1 hesitation(s), 1 halt(s)"
    assert f"<title>{title} marked</title>" in aperture
    # Every cycle is numbered at its turn, and the legend speaks of cycles.
    assert {str(k) for k in range(1, n + 1)} <= set(_texts(aperture))
    assert {"cycle peak", "cycle start", "hesitation", "halt"} <= set(_texts(aperture))

    amplitude = _plot(html, "amplitude")
    assert {f"amplitude ({unit})", "cycle number"} <= set(_texts(amplitude))
    slope = doc["metrics"]["amplitude_decrement_per_cycle"]
    over_all = f", all {n} cycles" if n > 10 else ""  # the summary beside it: the first 10
    assert f"decrement {slope:+.2f} {unit}/cycle{over_all}" in _texts(amplitude)
    assert f"<title>Amplitude of {n} cycles with decrement line" in amplitude

    velocity = _plot(html, "velocity")
    assert {f"peak velocity ({unit}/s)", towards, back, "cycle number"} <= set(_texts(velocity))

    paths = _plot(html, "paths")
    assert set(doc["markers"]) <= set(_texts(paths))
    for svg in (aperture, amplitude, velocity, paths):
        assert "thumb" not in svg and "tap" not in " ".join(_texts(svg))

    # The page around the plots says the same; the tables carry the units.
    assert f"{TITLE[task]} over time" in html
    assert "amplitude of each cycle" in html.lower()
    amp_key = task_key("amplitude_mm_mean", task)
    row = re.search(rf'<tr[^>]*data-metric="{amp_key}".*?</tr>', html, re.S)
    assert row and f">{unit}<" in row.group(0)
    cycles = re.search(r'<table class="taps">.*?</table>', html, re.S)
    assert cycles, "the table of cycles"
    heads = re.findall(r"<th[^>]*>([^<]*)</th>", cycles.group(0))
    assert heads[:6] == [
        "Cycle", "Start (s)", "Peak (s)", f"Amplitude ({unit})",
        f"{towards.capitalize()} ({unit}/s)", f"{back.capitalize()} ({unit}/s)",
    ]  # fmt: skip
    first = doc["cycles"][0]
    assert f"{first[task_key('amplitude_mm', task)]:.1f}" in cycles.group(0)


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_the_cycles_are_marked_where_the_signal_turns(task: Task) -> None:
    """The dots of the signal plot sit on the cycle peaks: the drawn peak heights are the
    signal at each cycle's turn, so a plot of another quantity (or unit) would not fit."""
    from app.reports.figures import signal_series
    from app.reports.result import read_result

    markers, doc, _ = task_trial(task.value, duration_s=DURATION_S[task], seed=3)
    series = signal_series(markers, task.value, side=read_result(doc).side)
    assert series is not None
    t, values, _ = series
    peaks = np.interp([c[task_key("t_max_aperture_s", task)] for c in doc["cycles"]], t, values)
    amp = np.array([c[task_key("amplitude_mm", task)] for c in doc["cycles"]])
    starts = np.interp([c["t_start_s"] for c in doc["cycles"]], t, values)
    # The raw signal's peak minus its start is the measured amplitude (filtering aside).
    tolerance = 0.5 if task.amplitude_unit == "deg" else 0.01 * amp  # degrees / 1 %
    assert np.all(np.abs((peaks - starts) - amp) <= tolerance + 0.2)  # + raw-sample noise


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_a_correction_of_a_task_is_measured_again_and_matches_the_truth(
    api: Api, seeded, db_sessionmaker, storage, task: Task
) -> None:
    hand = "left" if task is Task.PRONATION_SUPINATION else "right"  # the side matters there
    trial_id, original, truth = store_task_trial(db_sessionmaker, storage, task, hand=hand)
    h = api.headers
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"exclude_taps": [2], "dismiss_pauses": [3], "reason": "cycle 3 was a cough"},
        headers=h,
    )
    assert r.status_code == 201, r.text
    doc = api.client.get(f"/api/v1/trials/{trial_id}/result", headers=h).json()
    assert doc["revision"] == 2 and doc["task"] == task.value
    m = doc["metrics"]
    kept = [c for c in truth.cycles if c.index != 2]
    assert m["cycle_count"] == len(kept) == original["metrics"]["cycle_count"] - 1  # exact
    amp_key = task_key("amplitude_mm", task)
    amp = np.array([c[amp_key] for c in doc["cycles"]])
    true_amp = np.array([c.amplitude for c in kept])
    mean = m[task_key("amplitude_mm_mean", task)]
    assert m["amplitude_mean"] == mean and m["amplitude_unit"] == task.amplitude_unit
    if task.amplitude_unit == "deg":
        assert np.max(np.abs(amp - true_amp)) <= 0.5  # degrees
        assert abs(mean - np.mean(true_amp)) <= 0.5  # degrees
    else:
        assert np.max(np.abs(amp / true_amp - 1)) <= 0.01  # 1 %
        assert abs(mean / np.mean(true_amp) - 1) <= 0.01  # 1 %
    assert abs(m["frequency_hz"] / truth.frequency_hz - 1) <= 0.01  # 1 %
    assert abs(m["amplitude_decrement_per_cycle"] / truth.decrement_per_cycle - 1) <= 0.10
    assert m["hesitation_count"] == 0 and m["halt_count"] == 1  # the hesitation dismissed
    assert [c["index"] for c in doc["excluded_taps"]] == [2]
    assert doc["metrics_first_10"]["cycle_count"] == 10

    # Its stored plots are the corrected revision's, in the task's quantity.
    html = api.client.get(f"/api/v1/trials/{trial_id}/report.html", headers=h).text
    aperture = _plot(html, "aperture")
    signal, unit, _ = EXPECTED[task]
    assert f"{signal} ({unit})" in _texts(aperture)
    assert f"{len(kept)} cycles, 0 hesitation(s), 1 halt(s)" in aperture


def test_three_marker_labels_cannot_be_swapped(api: Api, seeded, db_sessionmaker, storage) -> None:
    trial_id, _, _ = store_task_trial(db_sessionmaker, storage, Task.TOE_TAPPING)
    r = api.client.post(
        f"/api/v1/trials/{trial_id}/revisions",
        json={"swap_labels": True, "reason": "labels look wrong"},
        headers=api.headers,
    )
    assert r.status_code == 422
    assert "named by their distances" in r.json()["detail"]


def test_the_patient_page_trends_each_task_in_its_own_metrics_and_units(
    client, seeded, db_sessionmaker, storage
) -> None:
    """Finger tapping (``seeded``: two visits), hand movements and toe tapping at both visits
    (plots), pronation–supination at one (a table): each task its own trends."""
    from app.reports.catalogue import format_metric
    from app.reports.task_metrics import trend_metrics

    docs = {}
    for task, sessions in (
        (Task.HAND_MOVEMENTS, (0, 1)),
        (Task.TOE_TAPPING, (0, 1)),
        (Task.PRONATION_SUPINATION, (1,)),
        (Task.LEG_AGILITY, (0, 1)),
    ):
        for k in sessions:
            # the amplitude falls from the first visit to the second (another trial)
            _, doc, _ = store_task_trial(
                db_sessionmaker, storage, task, session_index=k, seed=k,
                amplitude_scale=1.0 - 0.2 * k,
            )  # fmt: skip
            docs[(task, k)] = doc
    login(client)
    html = client.get(f"/patients/{seeded['patient_id']}").text
    # the sessions table holds feet and legs too: sides and cycles, not only hands and taps
    assert 'Right side <span class="unit">(first 10 taps or cycles)</span>' in html
    groups = re.findall(r'data-trend-task="([a-z_]+)"', html)
    assert groups == [
        "finger_tapping",
        "hand_movements",
        "pronation_supination",
        "toe_tapping",
        "leg_agility",
    ]
    sections = dict(
        re.findall(r'data-trend-task="([a-z_]+)"(.*?)</section>', html, re.S)
    )  # fmt: skip

    for task in (Task.HAND_MOVEMENTS, Task.TOE_TAPPING, Task.LEG_AGILITY):
        part = sections[task.value]
        unit = task.amplitude_unit
        keys = re.findall(r'<figure class="plot-figure trend" data-trend="([^"]+)"', part)
        assert keys == [key for key, _, _ in trend_metrics(task)]
        assert (
            task_key("amplitude_decrement_mm_per_tap", task)
            == f"amplitude_decrement_{unit}_per_cycle"
        )
        texts = _texts(part)
        assert {
            f"Mean amplitude ({unit})",
            f"Amplitude decrement ({unit}/cycle)",
            "Frequency (Hz)",
        } <= set(texts)
        towards = task.phase_words[0]
        assert f"Peak {towards} velocity ({unit}/s)" in texts
        # Each point's hover: the date, the side's limb, and that trial's first-10 value.
        for k, (day, med) in enumerate((("2024-03-01", "off"), ("2025-03-01", "on"))):
            first10 = docs[(task, k)]["metrics_first_10"]["amplitude_mean"]
            hover = f"{day} 09:00, right {task.limb}, medication {med}: {first10:.3g} {unit}"
            assert hover in part
        assert "thumb" not in part and "Tapping" not in part

    ps = sections[Task.PRONATION_SUPINATION.value]
    assert "data-trend-table" in ps and 'data-plot="trend"' not in ps  # one visit: a table
    rows = dict(
        re.findall(r'<tr data-trend="([^"]+)">(.*?)</tr>', ps, re.S)
    )  # fmt: skip
    first10 = docs[(Task.PRONATION_SUPINATION, 1)]["metrics_first_10"]
    for key, label, unit in trend_metrics(Task.PRONATION_SUPINATION):
        cells = re.findall(r"<t[dh][^>]*>([^<]*)</t[dh]>", rows[key])
        assert cells[0] == label
        expected = format_metric(key, first10[key], "pronation_supination")
        if key == "hesitation_count":  # interruptions: hesitations and halts
            expected = format_metric(key, first10[key] + first10["halt_count"])
        assert cells[1] == expected and cells[-1] == ("" if unit == "count" else unit)
    assert "amplitude_deg_mean" in rows and "supination_velocity_deg_s_max" in rows
    assert "deg/s" in ps and "right hand, medication on" in ps

    # Finger tapping keeps its own trends, untouched by the other tasks' trials.
    ft = sections["finger_tapping"]
    assert ft.count('data-plot="trend"') == 5 and "Tapping frequency (Hz)" in _texts(ft)


def test_only_trials_of_the_same_task_are_offered_and_compared(
    client, seeded, db_sessionmaker, storage
) -> None:
    """Leg agility in degrees beside finger tapping in millimetres would compare nothing:
    the trial page offers the same task's trials only, and refuses another task's."""
    legs = {
        hand: store_task_trial(db_sessionmaker, storage, Task.LEG_AGILITY, hand=hand)[0]
        for hand in ("right", "left")
    }
    login(client)
    html = client.get(f"/trials/{legs['right']}").text
    select = re.search(r'<select id="compare-select".*?</select>', html, re.S).group(0)
    offered = re.findall(r'<option value="(\d+)"[^>]*>([^<]*)</option>', select)
    assert [int(v) for v, _ in offered] == [legs["left"]]
    assert offered[0][1].endswith(", left leg, medication on (other leg, same session)")
    title = re.search(r"<title>([^<]*)</title>", html).group(1)
    assert ", right leg, medication on" in title
    r = client.get(f"/trials/{legs['right']}?compare={legs['left']}")
    assert "Compared trial" in r.text
    tapping = seeded["trials"][(1, "left")]
    r = client.get(f"/trials/{legs['right']}?compare={tapping}")
    assert r.status_code == 200 and "Compared trial" not in r.text
    assert "That trial measured finger tapping, this one leg agility" in r.text
    page = client.get(f"/trials/{tapping}").text
    select = re.search(r'<select id="compare-select".*?</select>', page, re.S).group(0)
    assert f'value="{legs["left"]}"' not in select and f'value="{legs["right"]}"' not in select


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_the_review_page_shows_the_task_s_signal_and_corrects_its_cycles(
    client, seeded, db_sessionmaker, storage, task: Task
) -> None:
    from app.reports.figures import signal_series
    from app.reports.result import read_result

    trial_id, doc, truth = store_task_trial(db_sessionmaker, storage, task)
    csrf = login(client)
    html = client.get(f"/trials/{trial_id}/review").text
    block = re.search(
        r'<script type="application/json" id="review-data">(.*?)</script>', html, re.S
    )
    data = json.loads(block.group(1))
    signal, unit, _ = EXPECTED[task]
    markers, _, _ = task_trial(task.value, duration_s=DURATION_S[task], seed=3)
    expected = signal_series(markers, task.value, side=read_result(doc).side)[1]
    # markers.csv keeps 0.1 µm, the page shows the signal to 0.01 (mm or deg): within 0.05
    np.testing.assert_allclose(np.array(data["signal"], float), expected, atol=0.05)
    assert data["unit"] == unit and data["peak_key"] == task_key("t_max_aperture_s", task)
    assert [c["index"] for c in data["taps"]] == [c["index"] for c in doc["cycles"]]
    assert data["pause_key"] == "cycle_index"
    # The overlay draws each marker in its plots' colour (all but the thumb and index
    # were purple, against a caption naming orange, blue and green)
    from app.plots import MARKER_COLOURS
    from core.protocols import protocol_for

    labels = protocol_for(task).labels
    assert data["marker_colours"] == {label: MARKER_COLOURS[k][0] for k, label in enumerate(labels)}
    # (the caption under the videos names the same colours: app.templating's marker_legend)
    assert f"{signal[0].upper()}{signal[1:]} ({unit}) over time" in html
    assert f'<th scope="col" class="num">Amplitude ({unit})</th>' in html
    assert "Cycle 3</button>" in html and "Tap " not in html
    # The pauses are listed at their cycle: the hesitation before cycle 3, the halt before 6.
    row3 = re.search(r'<tr data-tap-row="3".*?</tr>', html, re.S).group(0)
    assert "hesitation" in row3 and 'name="dismiss_pauses" value="3"' in row3
    swap = "Finger and wrist labels are the wrong way round"
    assert (swap in html) == (task is Task.HAND_MOVEMENTS)  # three markers: nothing to swap

    form = {"csrf_token": csrf, "kind": "correct", "exclude_taps": ["1"], "reason": "a cough"}
    r = client.post(f"/trials/{trial_id}/revisions", data=form, follow_redirects=False)
    assert r.status_code == 303, r.text[:300]
    with db_sessionmaker() as db:
        current = db.get(Trial, trial_id).result.document
    assert current["metrics"]["cycle_count"] == len(truth.cycles) - 1
    assert [c["index"] for c in current["excluded_taps"]] == [1]
    again = client.get(f"/trials/{trial_id}/review").text
    assert "Cycle 2</button> (excluded)" in again


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
def test_the_pdf_report_gives_the_task_s_metrics_with_units_and_plots(
    api: Api, seeded, db_sessionmaker, storage, tmp_path
) -> None:
    from app.reports.catalogue import metric_rows
    from app.reports.result import read_result

    task = Task.PRONATION_SUPINATION
    trial_id, doc, _ = store_task_trial(db_sessionmaker, storage, task)
    r = api.client.get(f"/api/v1/trials/{trial_id}/report.pdf", headers=api.headers)
    assert r.status_code == 200 and r.content.startswith(b"%PDF")
    (tmp_path / "r.pdf").write_bytes(r.content)
    text = subprocess.run(
        ["pdftotext", "-layout", str(tmp_path / "r.pdf"), "-"],
        check=True, capture_output=True, text=True,
    ).stdout  # fmt: skip
    lines = [" ".join(line.split()) for line in text.splitlines()]
    # Every primary metric: the first word of its label, its value, first-10 value and unit
    # on one line of the table (longer labels wrap onto the next lines).
    rows = metric_rows(read_result(doc))
    assert any(row.unit == "deg" for row in rows) and any(row.unit == "deg/s" for row in rows)
    for row in rows:
        cells = " ".join(v for v in (row.value, row.value_first_10, row.unit) if v)
        assert any(
            line.startswith(row.label.split()[0]) and f" {cells}" in line for line in lines
        ), row
    # The plots' words stay text in the PDF: the task's axes and units.
    for words in ("hand rotation angle (deg)", "peak velocity (deg/s)"):
        assert words in " ".join(lines)
    assert "thumb" not in text.lower()


def test_the_visit_report_draws_and_defines_each_task_in_its_own_units(
    api: Api, seeded, db_sessionmaker, storage
) -> None:
    for task in NEW_TASKS:
        store_task_trial(db_sessionmaker, storage, task, session_index=1)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    html = api.client.get(f"/api/v1/sessions/{session_id}/report.html", headers=api.headers).text
    apertures = re.findall(r'<svg[^>]*data-plot="aperture".*?</svg>', html, re.S)
    labels = [t for svg in apertures for t in _texts(svg) if t.endswith(("(mm)", "(deg)"))]
    # Finger tapping's two hands, then one trial of each other task: each its own axis.
    assert labels == ["thumb–index distance (mm)"] * 2 + [
        f"{EXPECTED[t][0]} ({EXPECTED[t][1]})" for t in NEW_TASKS
    ]
    definitions = re.search(r'<dl class="definitions">(.*?)</dl>', html, re.S).group(1)
    terms = re.findall(r"<dt>([^<]*)</dt>", definitions)
    assert "Finger tapping: Mean amplitude (mm)" in terms
    assert "Pronation–supination: Mean amplitude (deg)" in terms
    assert "Pronation–supination: Peak supination velocity (deg/s)" in terms
    assert "Toe tapping: Amplitude decrement (mm/cycle)" in terms


@pytest.mark.skipif(shutil.which("pdftotext") is None, reason="poppler-utils is not installed")
def test_the_visit_report_keeps_each_task_s_summary_on_one_page(
    api: Api, seeded, db_sessionmaker, storage, tmp_path
) -> None:
    """A clinician-style review found the five items' summary split over pages: a task's
    table begun on one page and ended on the next, the signature box alone on a page.
    Each task's summary (title, table, rating) is on one page now, the note on bands is
    printed once, and the summary with the signature box takes at most three pages."""
    from app.reports.summary import TASK_TITLES

    for task in NEW_TASKS:
        store_task_trial(db_sessionmaker, storage, task, session_index=1)
    with db_sessionmaker() as db:
        session_id = db.get(Trial, seeded["trials"][(1, "right")]).session_id
    url = f"/api/v1/sessions/{session_id}/report"
    html = api.client.get(f"{url}.html", headers=api.headers).text
    assert html.count('class="summary-note"') == 1
    r = api.client.get(f"{url}.pdf", headers=api.headers)
    assert r.status_code == 200
    (tmp_path / "visit.pdf").write_bytes(r.content)
    text = subprocess.run(
        ["pdftotext", str(tmp_path / "visit.pdf"), "-"], check=True, capture_output=True, text=True
    ).stdout
    pages = [" ".join(page.split()) for page in text.split("\f")]
    signature = next(i for i, page in enumerate(pages) if "Signature and date" in page)
    assert signature <= 2, f"the summary runs over {signature + 1} pages"
    assert "Interpretation" in pages[signature]
    for task in NEW_TASKS:
        title = TASK_TITLES[task.value]
        page = next(p for p in pages[: signature + 1] if title in p)
        table = page[page.index(title) :]
        rating = re.search(r"clinician's rating \(0–4\): (\S+)", table)
        assert rating is not None, (task, "the rating is not on the title's page")
        assert "Decrement onset" in table[: rating.start()], (task, "the table is split")


def test_the_exports_give_the_task_s_markers_and_metrics_with_units(
    api: Api, seeded, db_sessionmaker, storage
) -> None:
    """markers.csv (positions in mm under the protocol's labels) and the FHIR Bundle (each
    metric an Observation with its UCUM unit) of a pronation–supination trial."""
    task = Task.PRONATION_SUPINATION
    trial_id, doc, _ = store_task_trial(db_sessionmaker, storage, task)
    csv = api.client.get(f"/api/v1/trials/{trial_id}/markers.csv", headers=api.headers).text
    lines = csv.splitlines()
    assert lines[0] == "frame,time_s,marker,x_mm,y_mm,z_mm,status,reprojection_px"
    assert {line.split(",")[2] for line in lines[1:]} == {"radial", "ulnar", "distal"}
    bundle = api.client.get(f"/api/v1/trials/{trial_id}/fhir", headers=api.headers).json()
    quantities = {
        coding["code"]: r["resource"]["valueQuantity"]
        for r in bundle["entry"]
        if r["resource"]["resourceType"] == "Observation" and "valueQuantity" in r["resource"]
        for coding in r["resource"]["code"]["coding"]
    }
    expected = {
        "amplitude_deg_mean": "deg",
        "supination_velocity_deg_s_max": "deg/s",
        "amplitude_decrement_deg_per_cycle": "deg/{cycle}",
        "frequency_hz": "Hz",
    }
    for key, ucum in expected.items():
        assert quantities[key]["code"] == ucum, (key, quantities[key])
        assert quantities[key]["value"] == pytest.approx(doc["metrics"][key], abs=1e-6)


@pytest.mark.parametrize("task", NEW_TASKS, ids=lambda t: t.value)
def test_the_other_tasks_metric_wording_names_no_fingers_and_repeats_no_word(task: Task) -> None:
    """The finger-tapping definitions reworded for each task read as sentences: a
    clinician-style review found "complete cycles (cycles)" and "the movement stay still"."""
    import re

    from app.reports import catalogue

    for key in catalogue.METRICS:
        spec = catalogue.metric_spec(task_key(key, task), task.value)
        text = f"{spec.label}. {spec.definition}"
        assert not re.search(r"\b(\w+) \(\1\)", text), text
        pattern = r"\btaps?\b|thumb|the fingers|movement stay\b|cycles whose cycle"
        assert not re.search(pattern, text, re.I), text
