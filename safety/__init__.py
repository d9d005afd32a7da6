"""The safety layer: the state machine, the latched stop, watchdogs and motion limits.

Pure logic, thread-safe, no I/O and no clock: time is passed in as ``now`` (seconds).
See docs/safety.md.
"""

from .errors import InputError, LimitError, SafetyError, StateError
from .limits import ISO_10218_REDUCED_SPEED, SpeedLimiter, WorkspaceBox
from .states import Cause, SafetyState, SafetySupervisor, Transition
from .stop import LatchedStop, StopRecord
from .watchdogs import (
    CameraStallWatchdog,
    CovarianceWatchdog,
    DeadlineWatchdog,
    DriverSilenceWatchdog,
    StalePoseWatchdog,
    Trip,
    WatchdogSet,
)

__all__ = [
    "ISO_10218_REDUCED_SPEED",
    "CameraStallWatchdog",
    "Cause",
    "CovarianceWatchdog",
    "DeadlineWatchdog",
    "DriverSilenceWatchdog",
    "InputError",
    "LatchedStop",
    "LimitError",
    "SafetyError",
    "SafetyState",
    "SafetySupervisor",
    "SpeedLimiter",
    "StalePoseWatchdog",
    "StateError",
    "StopRecord",
    "Transition",
    "Trip",
    "WatchdogSet",
    "WorkspaceBox",
]
