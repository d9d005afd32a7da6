"""Command-line tools: `oralnav sim render`, `oralnav markers print`, `oralnav config
check` and the `oralnavd` stub, run in-process through their entry functions."""

from __future__ import annotations

import json
from pathlib import Path

import cv2

from oralnav.cli import main as cli
from oralnav.cli.sheets import read_png_dpi
from oralnav.daemon import main

ROOT = Path(__file__).resolve().parents[2]
ENDO_SCENE = ROOT / "config" / "examples" / "endoscope_view.toml"


def _one_json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out
    return json.loads(out[0])


def test_sim_render_writes_pngs_and_truth(tmp_path, capsys):
    """Issue 2 item 7: `oralnav sim render SCENE --out DIR` writes one PNG per camera and
    truth.json; --json prints exactly one JSON object."""
    assert cli.run(["sim", "render", str(ENDO_SCENE), "--out", str(tmp_path), "--json"]) == 0
    doc = _one_json(capsys)
    assert doc["frames"][0]["visible_corners"]["endoscope"]["effector"] > 10
    img = cv2.imread(str(tmp_path / "endoscope.png"), cv2.IMREAD_UNCHANGED)
    assert img.shape == (1080, 1920)
    truth = json.loads((tmp_path / "truth.json").read_text())
    cam = truth["cameras"]["endoscope"]
    assert cam["image"] == "endoscope.png" and cam["size"] == [1920, 1080]
    eff = cam["fields"]["effector"]
    assert len(eff["corner_ids"]) == len(eff["corners_px"]) == len(eff["obliquity_deg"])
    assert truth["reference"] == "endoscope"


def test_sim_render_frames_are_reproducible(tmp_path, capsys):
    """Issue 2 item 7: same scene + seed gives the same bytes, across runs of the tool."""
    for out in ("a", "b"):
        assert cli.run(["sim", "render", str(ENDO_SCENE), "--out", str(tmp_path / out),
                        "--frames", "2", "--seed", "11"]) == 0
    capsys.readouterr()
    for k in range(2):
        a = (tmp_path / "a" / f"frame_{k:04d}" / "endoscope.png").read_bytes()
        b = (tmp_path / "b" / f"frame_{k:04d}" / "endoscope.png").read_bytes()
        assert a == b
    assert (tmp_path / "a" / "frame_0000" / "endoscope.png").read_bytes() != \
        (tmp_path / "a" / "frame_0001" / "endoscope.png").read_bytes()


def test_sim_render_bad_scene_names_file_and_key(tmp_path, capsys):
    """Issue 2 bad input: a malformed scene gets one clear error naming file and key, exit
    status 2, and nothing is written."""
    bad = tmp_path / "bad.toml"
    bad.write_text(ENDO_SCENE.read_text().replace('rig = "../rigs/endoscope.toml"',
                                                  f'rig = "{ROOT}/config/rigs/endoscope.toml"')
                   .replace('fields = "../fields/cell.toml"',
                            f'fields = "{ROOT}/config/fields/cell.toml"')
                   .replace("blur_sigma_px = 1.2", "blur_sigma_px = -1.0"))
    out = tmp_path / "out"
    assert cli.run(["sim", "render", str(bad), "--out", str(out), "--json"]) == 2
    captured = capsys.readouterr()
    err = json.loads(captured.out)["error"]
    assert "bad.toml" in err and "[imaging] blur_sigma_px" in err
    assert not out.exists()


def test_markers_print_writes_true_scale_png(tmp_path, capsys):
    """Issue 2 item 6: `oralnav markers print FIELD --dpi N --out F.png` writes a sheet
    whose PNG carries the dpi, with the board at true scale."""
    out = tmp_path / "opener.png"
    assert cli.run(["markers", "print", "opener", "--dpi", "600", "--out", str(out),
                    "--json"]) == 0
    doc = _one_json(capsys)
    assert doc["board_mm"] == [36.0, 27.0]
    assert abs(read_png_dpi(out) - 600) < 0.01
    img = cv2.imread(str(out), cv2.IMREAD_GRAYSCALE)
    assert img.shape[1] == doc["image_px"][0]
    # the board spans 36 mm = 850.4 px at 600 dpi: a dark run starts at its origin
    x0, y0 = doc["board_origin_px"]
    assert img[y0 + 5, x0 + 5] < 128  # top-left square is black
    assert cli.run(["markers", "print", "nosuch", "--dpi", "600", "--out", str(out)]) == 2
    assert "no field 'nosuch'" in capsys.readouterr().err


def test_config_check_reports_errors_with_file_and_key(tmp_path, capsys):
    """Issue 2 item 3: `oralnav config check` validates a configuration; a broken one is
    refused naming file, section and key."""
    assert cli.run(["config", "check", "--json"]) == 0
    doc = _one_json(capsys)
    assert doc["backend"] == "sim" and set(doc["fields"]) == {"robot", "effector", "opener"}
    bad = tmp_path / "cfg.toml"
    bad.write_text((ROOT / "config" / "sim.toml").read_text()
                   .replace('rig = "rigs/', f'rig = "{ROOT}/config/rigs/')
                   .replace("max_speed = 0.25", "max_speed = 0.3"))
    assert cli.run(["config", "check", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "cfg.toml" in err and "[safety] max_speed" in err


def test_oralnavd_check_and_bad_config(tmp_path, capsys):
    """Issue 2 item 1: `oralnavd` loads and validates its configuration (the embedded
    simulation default, or --config FILE) and refuses a broken one before starting."""
    assert main.run(["--check", "--json"]) == 0
    doc = _one_json(capsys)
    assert doc["valid"] and doc["api"]["port"] == 8750
    assert main.run(["--check", "--api-port", "9100", "--json"]) == 0
    assert _one_json(capsys)["api"]["port"] == 9100
    bad = tmp_path / "d.toml"
    bad.write_text("[cell]\nbackend = 'sim'\nrig = 'x.toml'\nfields = 'y.toml'\nbogus = 1\n")
    assert main.run(["--config", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "d.toml" in err and "bogus" in err and "unknown key" in err


def test_bench_needle_tracking_flag_runs_the_tracking_chart(tmp_path, capsys, monkeypatch):
    """Issue 7 benchmarks: `oralnav bench needle --tracking` runs the Monte Carlo and the
    tracking speed/accuracy chart into the same folder, with the same seed and quickness,
    and --json still prints exactly one object (the Monte Carlo's summary). Both benches
    are replaced by recorders here; their own tests run them."""
    from oralnav.bench import needle, needle_tracking

    calls = []
    steps = {k: 0.5 for k in ("NG", "NH", "ND", "NR", "NP")}
    monkeypatch.setattr(needle, "main", lambda out, **kw: calls.append(("mc", out, kw))
                        or {"trials": 2, "overall": 0.5, "steps": steps,
                            "split": "development"})
    monkeypatch.setattr(needle_tracking, "main",
                        lambda out, **kw: calls.append(("tracking", out, kw)) or {})
    assert cli.run(["bench", "needle", "--trials", "2", "--seed", "7", "--quick",
                    "--tracking", "--out", str(tmp_path), "--json"]) == 0
    assert _one_json(capsys) == {"trials": 2, "overall": 0.5, "steps": steps}
    assert [c[0] for c in calls] == ["mc", "tracking"]
    assert calls[1][1] == tmp_path and calls[1][2] == {"quick": True, "seed": 7}
    calls.clear()
    assert cli.run(["bench", "needle", "--trials", "2", "--out", str(tmp_path)]) == 0
    assert [c[0] for c in calls] == ["mc"]
    assert calls[0][2]["seed"] == 0 and calls[0][2]["validation"] is False


def _stand_in_needle_main(monkeypatch, trials: int, split: str) -> list[dict]:
    """``bench.needle.main`` replaced by a stand-in that records its keyword arguments
    and succeeds every step of ``trials`` trials on ``split`` seeds; the calls."""
    from oralnav.bench import needle

    calls: list[dict] = []
    steps = {k: 1.0 for k in ("NG", "NH", "ND", "NR", "NP")}
    monkeypatch.setattr(needle, "main", lambda out, **kw: calls.append(kw)
                        or {"trials": trials, "overall": 1.0, "steps": steps, "split": split})
    return calls


def test_bench_needle_validation_runs_the_validation_seeds(tmp_path, capsys, monkeypatch):
    """Issue 36 item 2: `oralnav bench needle --validation` asks for the validation Monte
    Carlo; with --seed or --quick it is bad input (exit 2, naming the range) and runs
    nothing."""
    calls = _stand_in_needle_main(monkeypatch, 400, "validation")
    assert cli.run(["bench", "needle", "--validation", "--out", str(tmp_path)]) == 0
    assert calls[0]["validation"] is True and calls[0]["trials"] is None
    assert "400 trials on validation seeds" in capsys.readouterr().out
    for extra in (["--seed", "5"], ["--quick"]):
        assert cli.run(["bench", "needle", "--validation", *extra, "--out", str(tmp_path),
                        "--json"]) == 2
        assert "1000000" in _one_json(capsys)["error"]
    assert len(calls) == 1


def test_bench_needle_arm_error_is_passed_or_refused(tmp_path, capsys, monkeypatch):
    """Issue 36 (arm errors): `--arm-error 2 1` reaches the Monte Carlo as (mm, deg);
    a negative or non-finite value is bad input (exit 2, naming the option) and runs
    nothing."""
    calls = _stand_in_needle_main(monkeypatch, 2, "development")
    assert cli.run(["bench", "needle", "--trials", "2", "--arm-error", "2", "1", "--out",
                    str(tmp_path)]) == 0
    assert calls[0]["arm_error"] == (2.0, 1.0)
    capsys.readouterr()
    for bad in (["-1", "0"], ["1", "nan"]):
        assert cli.run(["bench", "needle", "--arm-error", *bad, "--out", str(tmp_path),
                        "--json"]) == 2
        assert "--arm-error takes two finite values >= 0" in _one_json(capsys)["error"]
    assert len(calls) == 1


def test_bench_needle_difficulty_runs_a_level_or_the_sweep(tmp_path, capsys, monkeypatch):
    """Issue 36 item 4: `--difficulty 1.5` runs the Monte Carlo at that difficulty;
    several values run the sweep (both procedures; --json prints one object with each
    procedure's success per level); a value outside 0..2, or a sweep with --servo or
    --tracking, is bad input (exit 2, naming the option) and runs nothing."""
    from oralnav.bench import needle

    calls = []
    steps = {k: 1.0 for k in ("NG", "NH", "ND", "NR", "NP")}

    def main(out, **kw):
        calls.append(kw)
        if len(kw["difficulty"]) == 1:
            return {"trials": 2, "overall": 1.0, "steps": steps, "split": "development"}
        pts = [{"overall": 0.5}, {"overall": 0.25}]
        return {"levels": kw["difficulty"], "trials": 2,
                "modes": {"open_loop": pts, "servoed": pts[::-1]}}

    monkeypatch.setattr(needle, "main", main)
    assert cli.run(["bench", "needle", "--trials", "2", "--difficulty", "1.5", "--out",
                    str(tmp_path)]) == 0
    assert calls[-1]["difficulty"] == [1.5]
    capsys.readouterr()
    assert cli.run(["bench", "needle", "--trials", "2", "--difficulty", "0", "2", "--out",
                    str(tmp_path), "--json"]) == 0
    assert _one_json(capsys) == {"levels": [0.0, 2.0], "trials": 2,
                                 "overall": {"open_loop": [0.5, 0.25],
                                             "servoed": [0.25, 0.5]}}
    for bad, why in ((["--difficulty", "2.5"], "--difficulty"),
                     (["--difficulty", "nan"], "--difficulty"),
                     (["--difficulty", "0", "1", "--servo"], "without --servo"),
                     (["--difficulty", "0", "1", "--tracking"], "without --servo")):
        assert cli.run(["bench", "needle", *bad, "--out", str(tmp_path), "--json"]) == 2
        assert why in _one_json(capsys)["error"]
    assert len(calls) == 2


def test_bench_needle_stream_is_passed_or_refused(tmp_path, capsys, monkeypatch):
    """Issue 36 item 1: `bench needle --stream` runs the servoed Monte Carlo fed by the
    tracking task (it implies --servo); `bench needle-stream`
    passes its seeds and camera rates, and refuses a negative rate or no trials (exit 2,
    naming the option) before recording anything."""
    from oralnav.bench import needle_stream

    calls = _stand_in_needle_main(monkeypatch, 2, "development")
    assert cli.run(["bench", "needle", "--trials", "2", "--stream", "--out",
                    str(tmp_path)]) == 0
    assert calls[-1]["servo"] is True and calls[-1]["stream"] is True
    capsys.readouterr()
    runs = []

    def main(out, seed, trials, fps):
        runs.append((seed, trials, list(fps)))
        r = {"fps": 30.0, "rate_hz": {"p50": 30.0}, "latency_ms": {"p50": 40.0, "p99": 50.0},
             "skipped": 0}
        return {"drives": trials, "replay": {"30": r}, "command_ms": {"p50": 1.0},
                "closed_loop": {"rate_hz": {"p50": 12.0}}, "met": True}

    monkeypatch.setattr(needle_stream, "main", main)
    assert cli.run(["bench", "needle-stream", "--seed", "7", "--trials", "2", "--fps", "30",
                    "--out", str(tmp_path), "--json"]) == 0
    assert runs == [(7, 2, [30.0])] and _one_json(capsys)["met"] is True
    for bad, why in ((["--fps", "-5"], "--fps"), (["--trials", "0"], "--trials")):
        assert cli.run(["bench", "needle-stream", *bad, "--out", str(tmp_path),
                        "--json"]) == 2
        assert why in _one_json(capsys)["error"]
    assert len(runs) == 1


def test_bench_needle_bad_counts_exit_2_naming_the_option(tmp_path, capsys):
    """issue 30: `oralnav bench needle --trials 0` (or --workers 0) is bad input: exit
    status 2 and a message naming the option, before any trial runs."""
    for option in ("--trials", "--workers"):
        assert cli.run(["bench", "needle", option, "0", "--out", str(tmp_path), "--json"]) == 2
        doc = _one_json(capsys)
        assert doc["exit"] == 2 and f"{option} must be at least 1, got 0" in doc["error"]
    assert not list(tmp_path.iterdir())


def test_unknown_flag_on_a_subcommand_prints_its_usage(capsys):
    """issue 30: an unknown flag on a subcommand prints that subcommand's usage (not the
    top-level one) and exits 2."""
    import pytest

    for argv, usage in ((["config", "check", "--bogus"], "usage: oralnav config check"),
                        (["bench", "needle", "--out", "x", "--bogus"],
                         "usage: oralnav bench needle"),
                        (["calibrate", "chain", "--samples", "a", "--out", "b", "--cell", "c",
                          "--bogus"], "usage: oralnav calibrate chain")):
        with pytest.raises(SystemExit) as ei:
            cli.run(argv)
        assert ei.value.code == 2
        err = capsys.readouterr().err
        assert err.startswith(usage), err
        assert "unrecognized arguments: --bogus" in err


def test_sim_peers_writes_a_loadable_hardware_cell(tmp_path):
    """Issue 8 (demo on protocol peers): `oralnav sim peers --out DIR --json` starts the
    peers, prints where its configuration is, writes a hardware-cell configuration that
    loads, and stops cleanly on `q`."""
    import json
    import subprocess
    import sys

    from oralnav.config.daemon import load_config

    cli = "from oralnav.cli.main import main; main()"
    proc = subprocess.Popen([sys.executable, "-c", cli, "sim", "peers",
                             "--out", str(tmp_path), "--no-cameras", "--json"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    try:
        doc = json.loads(proc.stdout.readline())
        cfg = load_config(doc["config"])
        assert cfg.settings.cell.backend == "hardware"
        assert cfg.settings.arm.ur.host == doc["ur_host"]
        assert cfg.settings.effector.modbus.port == doc["modbus_port"]
        assert cfg.settings.inputs.port == doc["estop"] and not cfg.settings.cameras
        out, err = proc.communicate("q\n", timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "peers stopped" in err
