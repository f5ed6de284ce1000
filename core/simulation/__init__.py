"""Simulated stereo recordings of the finger-tapping test with exact ground truth.

- :mod:`core.simulation.kinematics` — the tapping model (``simulate_tapping``).
- :mod:`core.simulation.render` — retro-reflective markers on camera images.
- :mod:`core.simulation.session` — videos + ``rig.json`` + ``truth.json``
  (``simulate_session``).
- :mod:`core.simulation.boards` — calibration-board recordings.

See ``docs/simulator.md`` for the models and the ``truth.json`` format.
"""
