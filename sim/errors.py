"""Exception base of the simulator (``oralnav.sim``: the simulated world and the protocol
peers).

:class:`SimError` is the base of what the simulator raises: a scene it cannot render as asked
(:class:`~oralnav.sim.world.render.RenderError`, and the cell's
:class:`~oralnav.sim.world.cell.CellError`), a simulated measurement lost too often
(:class:`~oralnav.sim.world.calibration_chain.MeasurementLost`), a protocol peer that cannot
be set up (:class:`~oralnav.sim.peers.gige_fake.NoLoopbackAddress`). Each of those is also the
built-in type it was before (``ValueError`` or ``RuntimeError``), so existing ``except``
clauses still catch it.
"""


class SimError(Exception):
    """Base of every error raised by ``oralnav.sim``."""
