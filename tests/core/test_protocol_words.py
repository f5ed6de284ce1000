"""Each task's markers in words, for the messages a clinician or technician reads.

A failed pronation-supination analysis told the technician to "check that both cameras
see the thumb and index markers": that task has three hand markers and no thumb marker.
"""

from __future__ import annotations

import pytest

from core.protocols import protocol_for
from core.tasks import Task


@pytest.mark.parametrize("task", list(Task))
def test_every_task_names_its_own_markers(task: Task) -> None:
    protocol = protocol_for(task)
    words = protocol.markers_in_words
    assert words.startswith("the ") and "markers" in words, words
    if task is Task.PRONATION_SUPINATION:  # the cluster's labels are not words for people
        assert "three" in words and "hand" in words
    else:
        assert all(label in words for label in protocol.labels), (protocol.labels, words)
    others = {label for t in Task if t is not task for label in protocol_for(t).labels}
    assert not {w.strip(",") for w in words.split()} & (others - set(protocol.labels)), words
