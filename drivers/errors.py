"""Exception hierarchy of the hardware layer (``oralnav.drivers``).

Every error raised by driver code derives from :class:`DriverError`, so callers (the daemon,
the CLI) can catch the layer as a whole and still tell the kinds apart:

- :class:`DriverInitError`: a device or recording cannot be opened or set up (bad argument,
  missing path, unreadable file, unknown backend). Raised by constructors and ``start()``.
- :class:`DriverIOError`: an opened device failed while in use (lost frame, undecodable
  frame, read before ``start()`` or after ``close()``).
- :class:`DriverTimeoutError`: a device did not answer in time.
- :class:`ClockError`: a device's clock went back or jumped: its timestamps cannot be
  placed on the host's clock (a fault, not a read to retry).
- :class:`EndOfStream`: a finite source (a recording) has no more data.
"""


class DriverError(Exception):
    """Base of every error raised by ``oralnav.drivers``."""


class DriverInitError(DriverError):
    """A device or recording cannot be opened or configured; the message names it."""


class DriverIOError(DriverError):
    """A started device failed during I/O, or was used outside ``start()`` ... ``close()``."""


class DriverTimeoutError(DriverError, TimeoutError):
    """A device did not answer within its deadline (also a built-in ``TimeoutError``)."""


class ClockError(DriverIOError):
    """A device's clock went back, stood still or jumped, so its timestamps cannot be mapped
    onto the host's clock; the message says by how much. The frame is not delivered."""


class EndOfStream(DriverIOError):
    """A finite source (a replayed recording without ``loop``) has delivered its last frame.

    A subclass of :class:`DriverIOError` so code that treats any read failure alike still
    catches it; catch it first where the end of a recording is the normal way out.
    """
