"""``oralnav report`` (issue 35): the experiment list, and bad input refused with exit 2
before anything runs: an unknown experiment, an occupied output folder, a bad worker
count, an unreachable scheduler."""

from __future__ import annotations

import json

from oralnav.bench.report.experiments import all_experiments
from oralnav.cli import main as cli

#: Dask's threads, kept for the process once a client was tried (tests/conftest.py)
LONG_LIVED_THREADS = ("Dask-", "IO loop", "AsyncProcess Dask", "QueueFeederThread")


def test_list_names_every_experiment(capsys):
    """--list prints each key with its estimated quick and full time."""
    assert cli.run(["report", "--list"]) == 0
    out = capsys.readouterr().out
    for e in all_experiments():
        assert e.key in out
    for key in ("000/table1", "000/fig9", "000/fig11", "000/table2", "000/fig13"):
        assert key in out


def test_unknown_experiment_refused(tmp_path, capsys):
    code = cli.run(["report", "--out", str(tmp_path / "r"), "--only", "000/table9", "--json"])
    assert code == 2
    err = json.loads(capsys.readouterr().out)["error"]
    assert "000/table9" in err and "000/table1" in err
    assert not (tmp_path / "r").exists()  # refused before anything was written


def test_occupied_folder_refused(tmp_path, capsys):
    (tmp_path / "mine.txt").write_text("keep")
    assert cli.run(["report", "--out", str(tmp_path), "--only", "000/fig11"]) == 2
    assert "--force" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.txt"]


def test_bad_workers_and_unreachable_scheduler(tmp_path, capsys, monkeypatch):
    assert cli.run(["report", "--out", str(tmp_path / "r"), "--workers", "0"]) == 2
    assert "--workers" in capsys.readouterr().err
    from oralnav.bench import executor

    monkeypatch.setattr(executor, "CONNECT_TIMEOUT_S", 1.0)
    code = cli.run(["report", "--out", str(tmp_path / "r"), "--scheduler",
                    "tcp://127.0.0.1:9"])
    assert code == 2
    assert "tcp://127.0.0.1:9" in capsys.readouterr().err


def test_config_file_sets_the_scheduler(tmp_path, capsys, monkeypatch):
    """[report] scheduler and workers come from --config where the options leave them
    unset; a bad key or value is refused naming the file and the key."""

    seen = {}

    def fake_run(out, chosen, settings, force, say):
        seen.update(scheduler=settings.scheduler, workers=settings.workers)
        return {"complete": True, "experiments": {}}

    monkeypatch.setattr("oralnav.bench.report.run.run_report", fake_run)
    cfg = tmp_path / "lab.toml"
    cfg.write_text('[report]\nscheduler = "local"\nworkers = 3\n')
    assert cli.run(["report", "--out", str(tmp_path / "r"), "--config", str(cfg)]) == 0
    assert seen == {"scheduler": "local", "workers": 3}
    assert cli.run(["report", "--out", str(tmp_path / "r"), "--config", str(cfg),
                    "--workers", "1"]) == 0
    assert seen["workers"] == 1
    cfg.write_text('[report]\nschedular = "local"\n')
    assert cli.run(["report", "--out", str(tmp_path / "r"), "--config", str(cfg)]) == 2
    assert "schedular" in capsys.readouterr().err
