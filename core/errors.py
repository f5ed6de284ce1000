"""Domain errors whose messages are written for a clinician or a technician.

Each message is one sentence that says what was wrong and what to do about it.
Programming errors (wrong shapes, wrong types) raise ``ValueError`` instead.
"""


class BradyscopeError(Exception):
    """A measurement could not be made; the message says why and what to do."""


class InputError(BradyscopeError):
    """An input file is unreadable, of the wrong kind, or inconsistent with another."""


class RigFileError(InputError):
    """A rig file is malformed, of an unknown format version, or inconsistent."""


class CalibrationError(BradyscopeError):
    """A calibration could not be computed or is not good enough."""


class DetectionError(BradyscopeError):
    """Markers (or a board) could not be found in the recording."""
