"""Exception hierarchy of the safety layer (``oralnav.safety``).

- :class:`SafetyError`: base of every error the safety layer raises.
- :class:`StateError`: a request that the current safety state does not allow (start while
  in FAULT, reset while the e-stop input is still pressed...). The message says why; the
  REST API answers it with 409 and changes nothing.
- :class:`LimitError`: a command or target outside a configured limit (speed, workspace).
- :class:`InputError`: a malformed argument (shape, finiteness, sign).
"""


class SafetyError(Exception):
    """Base of every error raised by ``oralnav.safety``."""


class StateError(SafetyError):
    """The request is not allowed in the current safety state; the message says why."""


class LimitError(SafetyError, ValueError):
    """A command or target lies outside a configured limit; the message names it."""


class InputError(SafetyError, ValueError):
    """An argument is malformed (wrong shape, not finite, negative where a size is needed);
    a programming or wiring error rather than a limit being reached."""
