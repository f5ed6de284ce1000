"""Simulated stereo recordings of the finger-tapping test with exact ground truth.

- :mod:`core.simulation.kinematics` — the tapping model (``simulate_tapping``).
- :mod:`core.simulation.rig` — a realistic default stereo rig (``default_rig``).
- :mod:`core.simulation.render` — retro-reflective markers on camera images.
- :mod:`core.simulation.session` — videos + ``rig.json`` + ``truth.json``
  (``simulate_session``).
- :mod:`core.simulation.boards` — calibration-board recordings.

See ``docs/simulator.md`` for the models and the ``truth.json`` format.
"""

from core.simulation.kinematics import TappingScenario, TappingTruth, simulate_tapping
from core.simulation.rig import default_rig

__all__ = ["TappingScenario", "TappingTruth", "default_rig", "simulate_tapping"]
