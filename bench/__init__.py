"""Benchmarks (``./dev.sh bench [NAME]`` or ``python -m bench [NAME]``); figures go to
``bench/out/``. Long measurements live here, not in the timed test suite."""
