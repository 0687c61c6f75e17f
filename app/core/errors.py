"""The small exception hierarchy of lightflow.

Every error a user can cause (a bad file, a missing device, a wrong option)
is a :class:`LightflowError`.  The command line prints its message on one line
and exits with status 2; it never prints a traceback for these.
"""


class LightflowError(Exception):
    """Base class of every error that is reported to the user as one line."""


class ConfigError(LightflowError):
    """A rig, recording, session or option is malformed (names file and field)."""


class FrameError(LightflowError):
    """A frame file is missing, unreadable or of the wrong size."""


class OutputError(LightflowError):
    """An output (export, recording, .rrd) could not be written, e.g. a full disk."""


class OutputClosed(LightflowError):
    """The user closed an output window (the Rerun viewer): the run stops as after Ctrl-C,
    every output complete.  Raised by a sink's ``write``; the runner stops on it."""


class DriverError(LightflowError):
    """A camera or pattern output failed or could not be opened."""


class DeviceLostError(DriverError):
    """A device disappeared while streaming."""


class CalibrationError(LightflowError):
    """A calibration session cannot be calibrated (names pose, projector, frame)."""
