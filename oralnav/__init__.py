"""oralnav: navigation and control daemon of an automated oral-surgery suturing robot.

The repository's top-level folders import as subpackages of this namespace:
``oralnav.control`` (math, no I/O), ``oralnav.config`` (schemas and shipped files),
``oralnav.sim`` (scene simulator), ``oralnav.drivers``, ``oralnav.safety``, ``oralnav.daemon``.
"""

__version__ = "0.1.0"
