"""Exception base of the real-time layer (``oralnav.realtime``).

:class:`RealtimeError` is the base of the errors the control process and its channels to the
daemon raise: a shared record that cannot be created, attached or read
(:class:`~oralnav.realtime.shm.ShmError`), a plan channel that cannot carry a plan
(:class:`~oralnav.realtime.plan_channel.ChannelError`). Each of those is also the built-in
type it was before (``RuntimeError``), so existing ``except`` clauses still catch it.
"""


class RealtimeError(Exception):
    """Base of every error raised by ``oralnav.realtime``."""
