"""Exception base of the daemon layer (``oralnav.daemon``).

:class:`DaemonError` is the base of the errors the daemon's own modules raise (the audit
log's :class:`~oralnav.daemon.audit.AuditError`, ...), so a caller can catch the layer as a
whole and still tell the kinds apart. Errors of the layers the daemon drives (control,
drivers, safety, config) pass through with their own types.
"""


class DaemonError(Exception):
    """Base of every error raised by ``oralnav.daemon`` itself."""
