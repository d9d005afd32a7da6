"""``oralnav report``: the seeds' experiments run in simulation, each beside the paper's
figures, in one self-contained HTML page and one JSON document (issue 35).

- :mod:`.section`: one experiment's result (rows of paper figure, ours, target) and its
  computed verdict;
- :mod:`.experiments`: the registry of experiments, keyed like ``"000/table1"``;
- :mod:`.seed000`, :mod:`.seed002`, :mod:`.seed004`, :mod:`.stability`: the experiments;
- :mod:`.charts`: the chart conventions (units on every axis, one quantity per axis);
- :mod:`.page`: ``index.html``;
- :mod:`.run`: the run: output folder, resume, progress, a failed experiment's section.
"""
