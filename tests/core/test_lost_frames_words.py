"""Lost frames in words: grouped by gap, a long list summed up (core.timing, core.pipeline).

A browser take of 161 frames (trial 17 of a clinic day) lost frames in 33 gaps; its
warning listed "left after frames [0, 2, 2, 2, 2, 2, 2, 2, 17, ..., 159]", 78 numbers a
camera, over two pages of the signed PDF.
"""

from __future__ import annotations

import inspect

import numpy as np

import core.clock
from core.pipeline import _CLOCK_LOST_FRAMES, _lost_frames_in_words
from core.timing import FROM_FILE, FrameTimes, describe_lost_frames, lost_frame_gaps

# Trial 17's left camera: sync.dropped_frames_left, one entry per lost frame.
TRIAL_17 = [0, 2, 2, 2, 2, 2, 2, 2, 17, 28, 28, 29, 31, 32, 34, 35, 35, 38, 95]
TRIAL_17 += [100] * 5 + [102, 111, 111, 123, 124, 125] + [126] * 5 + [127, 132, 132, 133]
TRIAL_17 += [138] * 3 + [139, 139, 140, 142, 142, 142, 147, 147, 149, 153, 154] + [155] * 13
TRIAL_17 += [157] * 5 + [158] * 4 + [159] * 3


def test_a_repeated_frame_number_is_one_gap_of_several_frames():
    assert len(TRIAL_17) == 78
    gaps = lost_frame_gaps(TRIAL_17)
    assert len(gaps) == 33 and sum(n for _, n in gaps) == 78
    assert gaps[:3] == [(0, 1), (2, 7), (17, 1)] and (155, 13) in gaps
    # FrameTimes counts each gap's frames from its length: 257 ms at 30 Hz is 7 lost.
    t = np.array([0.0, 0.033, 0.067, 0.324, 0.357])  # s
    times = FrameTimes(t, 30.0, FROM_FILE)
    assert times.dropped_after == [2] * 7
    assert lost_frame_gaps(times.dropped_after) == [(2, 7)]


def test_few_gaps_are_named_and_many_summed_up():
    assert describe_lost_frames([]) == "no frames lost"
    assert describe_lost_frames([2, 2, 2]) == "3 frames lost after frame 2"
    assert describe_lost_frames([4]) == "1 frame lost after frame 4"
    assert describe_lost_frames([17, 2, 2, 2]) == "3 frames lost after frame 2 and 1 after frame 17"
    text = describe_lost_frames(TRIAL_17, fps=29.678)
    # 13 lost frames are 14 intervals of 33.7 ms between the frames either side.
    assert text == "78 frames lost in 33 gaps; the longest, 13 frames (472 ms), after frame 155"
    assert "ms" not in describe_lost_frames(TRIAL_17)  # no rate, no duration


def test_the_time_models_warning_says_the_gaps_not_every_frame_number():
    # core.clock words it; this rewording finds it by how it starts
    assert _CLOCK_LOST_FRAMES.strip() in inspect.getsource(core.clock)
    clock_words = (
        "149 frames were lost during the recording (left after frames"
        f" {TRIAL_17}, right after frames [0, 2, 2]); the positions around them are"
        " interpolated or missing; record with less load on the computer"
    )
    times = (FrameTimes(np.arange(5) / 29.678, 29.678), FrameTimes(np.arange(5) / 30.0, 30.0))
    sync = {"dropped_frames_left": TRIAL_17, "dropped_frames_right": [0, 2, 2]}
    other = "the cameras' clocks differ by 900 ppm"
    got = _lost_frames_in_words([other, clock_words], sync, times)
    assert got[0] == other
    assert got[1] == (
        "149 frames were lost during the recording (left camera: 78 frames lost in 33 gaps;"
        " the longest, 13 frames (472 ms), after frame 155; right camera: 1 frame lost after"
        " frame 0 and 2 after frame 2); the positions around them are interpolated or"
        " missing; record with less load on the computer"
    )
