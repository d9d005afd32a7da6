"""Exception hierarchy of the math layer (``oralnav.control``).

Every error raised by control code derives from :class:`ControlError`, so callers (the
daemon, the CLI) can catch the layer as a whole and still tell the kinds apart.
"""


class ControlError(Exception):
    """Base of every error raised by ``oralnav.control``."""


class GeometryError(ControlError, ValueError):
    """A transform or rotation is malformed (wrong shape, not finite, not a rotation)."""


class CameraModelError(ControlError, ValueError):
    """A camera model is malformed (bad intrinsics, distortion or image size)."""


class MarkerFieldError(ControlError, ValueError):
    """A marker field is malformed (unknown dictionary, id overflow, impossible surface)."""


class CalibrationError(ControlError, ValueError):
    """A calibration was refused: too few or degenerate samples, or samples that disagree
    beyond what the measurement noise explains. The message says what to capture instead."""


class PlanningError(ControlError, ValueError):
    """A planning input was refused: a mesh the surrogate model cannot fit (empty, not
    enclosing a slice origin), a hole outside the model, or bad optimiser settings."""


class AdmittanceError(ControlError, ValueError):
    """Bad admittance settings or input (non-finite force, bad ``dt``, a start position
    outside the fixture); the message names the value. The state is left untouched."""


class NeedleError(ControlError, ValueError):
    """A needle task was refused before any motion: a needle or suture geometry the
    drive cannot follow (suture depth beyond the radius), an unreachable grasp, or a
    tracker that has not converged. The message names the value and the reason."""


class StepOrderError(ControlError):
    """A procedure step was asked for out of turn or is unknown; the daemon answers it
    with 409."""
