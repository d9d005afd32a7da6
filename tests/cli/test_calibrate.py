"""`oralnav calibrate ...` (issue 5 items 5-7): simulated capture, every chain calibration
from the recorded sample files, the calibration files they write, and bad input that must
leave the previous calibration in place."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from oralnav.cli import calibrate
from oralnav.cli import main as cli
from oralnav.config.calibration import load_calibration
from oralnav.config.cell import load_cell_config
from oralnav.config.daemon import load_config
from oralnav.control.geometry import invert, pose_error
from oralnav.daemon.navigation_task import nav_calibration

ROOT = Path(__file__).resolve().parents[2]
G = load_cell_config(ROOT / "config" / "examples" / "sim_cell.toml").geometry


def _json(capsys) -> dict:
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1, out
    return json.loads(out[0])


def _err(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    dt, dr = pose_error(T, T_true)
    return dt * 1e3, float(np.degrees(dr))


@pytest.fixture(scope="module")
def chain(tmp_path_factory) -> tuple[Path, Path]:
    """A simulated capture (15 samples at 0.15 px) and the chain calibrated from it."""
    root = tmp_path_factory.mktemp("cal")
    assert cli.run(["calibrate", "capture", "--out", str(root / "samples"), "--samples", "15",
                    "--seed", "3"]) == 0
    assert cli.run(["calibrate", "chain", "--samples", str(root / "samples"), "--out",
                    str(root / "cal"), "--cell", "oralnav-sim"]) == 0
    return root / "samples", root / "cal"


def test_capture_writes_every_sample_file(chain):
    """Item 7: the simulated arm records each calibration's samples as text matrices."""
    samples, _ = chain
    doc = json.loads((samples / "capture.json").read_text())
    for kind, files in calibrate.CAPTURE_FILES.items():
        for f in files:
            T = np.loadtxt(samples / kind / f).reshape(-1, 4, 4)
            assert len(T) == (150 if kind == "pivot" else 15), (kind, f)
    assert doc["corner_noise_px"] == 0.15


def test_chain_recovers_the_simulated_truth(chain):
    """Targets: hand-eye within 0.05 deg and 0.2 mm of the simulator's truth, through the
    whole capture-and-calibrate path; the other links within 0.2 mm and 0.2 deg."""
    _, cal = chain
    he = load_calibration(cal / "hand_eye.toml", kind="hand_eye", cell="oralnav-sim")
    mm, deg = _err(he["T_B_C"], G.T_B_C)
    assert mm < 0.2 and deg < 0.05, (mm, deg)
    checks = {"endoscope_opener": ("T_OM_En", G.T_OM_En),
              "effector_zero": ("T_RM_E0", invert(G.T_tcp_RM) @ G.T_tcp_E0),
              "effector_marker": ("T_EM_E", invert(G.T_E_EM))}
    for kind, (key, truth) in checks.items():
        c = load_calibration(cal / f"{kind}.toml", kind=kind)
        mm, deg = _err(c[key], truth)
        assert mm < 0.2 and deg < 0.2, (kind, mm, deg)
        assert c.samples.count == 15 and len(c.samples.sha256) == 64
        assert c.residuals["samples_used"] >= 10
    assert len(he.residuals["per_pose_mm"]) == 15


def test_daemon_navigates_on_the_calibration_files(chain, tmp_path):
    """Item 6: the daemon configuration names the files; navigation uses their values."""
    _, cal = chain
    text = (ROOT / "config" / "sim.toml").read_text()
    text = text.replace('"rigs/', f'"{ROOT}/config/rigs/').replace(
        '"fields/', f'"{ROOT}/config/fields/').replace('"examples/', f'"{ROOT}/config/examples/')
    # the shipped [calibration] section, pointed at this test's files and cell
    text = text.replace('"calibration/', f'"{cal}/').replace('cell = "sim-cell"',
                                                             'cell = "oralnav-sim"')
    path = tmp_path / "oralnav.toml"
    path.write_text(text)
    cfg = load_config(path)
    assert all(c.source.startswith(str(cal)) for c in cfg.calibrations.values())
    nav = nav_calibration(cfg.calibrations)   # no cell: every kind must come from a file
    np.testing.assert_array_equal(nav.T_B_C, cfg.calibrations["hand_eye"]["T_B_C"])
    np.testing.assert_array_equal(nav.T_EM_E, cfg.calibrations["effector_marker"]["T_EM_E"])
    with pytest.raises(KeyError, match="hand_eye"):
        nav_calibration({})


def test_hand_eye_cli_reports_per_pose_residuals(chain, capsys):
    samples, _ = chain
    assert cli.run(["calibrate", "hand-eye", "--robot", str(samples / "hand_eye/T_B_tcp.txt"),
                    "--marker", str(samples / "hand_eye/T_C_RM.txt"), "--json"]) == 0
    doc = _json(capsys)
    assert len(doc["per_pose_mm"]) == 15 and doc["rms_mm"] < 0.2
    assert doc["out"] is None


def test_refused_calibration_keeps_the_previous_file(chain, tmp_path, capsys):
    """Bad input: rotations about one axis only (degenerate for hand-eye) exit 2 with a
    message saying so, and the existing calibration file is untouched."""
    samples, cal = chain
    out = tmp_path / "hand_eye.toml"
    out.write_bytes((cal / "hand_eye.toml").read_bytes())
    before = out.read_bytes()
    T = np.loadtxt(samples / "hand_eye/T_B_tcp.txt").reshape(-1, 4, 4)
    from scipy.spatial.transform import Rotation
    spin = Rotation.from_rotvec(np.linspace(-0.4, 0.4, len(T))[:, None] * [0, 0, 1.0])
    T[:, :3, :3] = spin.as_matrix()
    robot = tmp_path / "T_B_tcp.txt"
    np.savetxt(robot, T.reshape(-1, 4))
    code = cli.run(["calibrate", "hand-eye", "--robot", str(robot), "--marker",
                    str(samples / "hand_eye/T_C_RM.txt"), "--out", str(out),
                    "--cell", "oralnav-sim", "--json"])
    assert code == 2
    assert "axis" in _json(capsys)["error"]
    assert out.read_bytes() == before


@pytest.mark.parametrize("content, match", [
    ("1 2 3\n4 5 6\n", "4N rows of 4 numbers"),
    ("1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n" * 2 + "1 0 0\n", "not a table of numbers"),
    ("nan 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "non-finite"),
    ("2 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n", "not rigid"),
])
def test_malformed_sample_files_name_file_and_problem(tmp_path, capsys, content, match):
    """Bad input: a file of the wrong shape, NaNs, non-rigid matrices: exit 2, the file named."""
    bad = tmp_path / "T_C_OM.txt"
    bad.write_text(content)
    code = cli.run(["calibrate", "endoscope-opener", "--opener", str(bad), "--board-camera",
                    str(bad), "--board-endoscope", str(bad), "--json"])
    assert code == 2
    err = _json(capsys)["error"]
    assert match in err and str(bad) in err


def test_sample_files_of_different_lengths_are_refused(chain, tmp_path, capsys):
    samples, _ = chain
    short = tmp_path / "T_C_CB.txt"
    short.write_text("\n".join((samples / "endoscope_opener/T_C_CB.txt").read_text()
                               .splitlines()[:16]) + "\n")
    code = cli.run(["calibrate", "endoscope-opener",
                    "--opener", str(samples / "endoscope_opener/T_C_OM.txt"),
                    "--board-camera", str(short),
                    "--board-endoscope", str(samples / "endoscope_opener/T_En_CB.txt"),
                    "--json"])
    assert code == 2 and "same instants" in _json(capsys)["error"]


def test_out_without_cell_is_refused(tmp_path, capsys):
    code = cli.run(["calibrate", "hand-eye", "--robot", "x", "--marker", "y", "--out",
                    str(tmp_path / "he.toml"), "--json"])
    assert code == 2 and "--cell" in _json(capsys)["error"]


def test_chain_names_the_samples_folder_and_what_is_missing(tmp_path, capsys):
    """issue 30: `oralnav calibrate chain --samples out/nope` names the folder the user gave
    to --samples and what is missing, never a step's own option (--robot) the user did not
    type, and writes nothing."""
    out = tmp_path / "cal"
    nope = tmp_path / "nope"
    assert cli.run(["calibrate", "chain", "--samples", str(nope), "--out", str(out),
                    "--cell", "sim-cell", "--json"]) == 2
    err = _json(capsys)["error"]
    assert err.startswith(f"{nope}: --samples: no such folder") and "--robot" not in err
    part = tmp_path / "part"
    (part / "hand_eye").mkdir(parents=True)
    (part / "hand_eye" / "T_B_tcp.txt").write_text(" ".join(["1"] * 16) + "\n")
    assert cli.run(["calibrate", "chain", "--samples", str(part), "--out", str(out),
                    "--cell", "sim-cell", "--json"]) == 2
    err = _json(capsys)["error"]
    assert err.startswith(f"{part}: --samples: not a complete capture folder")
    assert "hand_eye/T_C_RM.txt" in err and "T_B_tcp" not in err and "--robot" not in err
    assert not out.exists()


# -- intrinsics and stereo from images (item 1) ---------------------------------------------
@pytest.fixture(scope="module")
def stereo_views(tmp_path_factory) -> Path:
    """16 rendered board views through the simulated stereo rig, as PNGs."""
    out = tmp_path_factory.mktemp("views")
    assert cli.run(["calibrate", "capture-views", "--rig", str(ROOT / "config/rigs/stereo.toml"),
                    "--out", str(out), "--views", "16"]) == 0
    return out


def test_stereo_from_images_recovers_focal_and_baseline(stereo_views, tmp_path, capsys):
    """Targets: focal length within 0.1 % and the stereo baseline within 0.05 mm of the
    simulated rig, from PNG images through `oralnav calibrate stereo`; the calibration file
    nests the rig and --rig-out writes a loadable rig file."""
    from oralnav.config.rig import load_rig

    v = stereo_views
    assert cli.run(["calibrate", "stereo", "--left", str(v / "left"), "--right", str(v / "right"),
                    "--fields", str(v / "board.toml"), "--out", str(tmp_path / "stereo.toml"),
                    "--cell", "sim-cell", "--rig-out", str(tmp_path / "rig.toml"),
                    "--json"]) == 0
    doc = _json(capsys)
    truth = load_rig(ROOT / "config/rigs/stereo.toml")
    assert abs(doc["baseline_m"] - 0.1) < 0.05e-3
    rig = load_rig(tmp_path / "rig.toml")
    for name in ("left", "right"):
        f, f_true = rig[name].K[0, 0], truth[name].K[0, 0]
        assert abs(f / f_true - 1) < 1e-3, (name, f)
    cal = load_calibration(tmp_path / "stereo.toml", kind="stereo", cell="sim-cell")
    np.testing.assert_allclose(cal["rig"]["right"].T_ref_cam, rig["right"].T_ref_cam)


def test_camera_from_images_refuses_too_few_views(stereo_views, tmp_path, capsys):
    """Bad input: four images are too few for intrinsics; exit 2, nothing written."""
    few = tmp_path / "few"
    few.mkdir()
    for p in sorted((stereo_views / "left").iterdir())[:4]:
        (few / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "cam.toml"
    code = cli.run(["calibrate", "camera", "--images", str(few), "--fields",
                    str(stereo_views / "board.toml"), "--out", str(out), "--cell", "c",
                    "--json"])
    assert code == 2 and "view" in _json(capsys)["error"]
    assert not out.exists()


# -- calibration targets users already have (issue 34) ---------------------------------------
SAMPLE = ROOT / "tests" / "data" / "opencv_stereo_chessboard"
SAMPLE_FIELDS = """\
# OpenCV's stereo sample board: 9 x 6 inner corners; its square side is not published,
# 25 mm is assumed (lengths, the baseline among them, scale with it)
[fields.sample]
family = "chessboard"
inner_corners = [9, 6]
square = 0.025
"""


def _opencv_corners(folder: Path, names: list[str], half: int = 5) -> list[np.ndarray]:
    """OpenCV's own corners: findChessboardCorners (adaptive threshold, normalised image,
    as its stereo_calib.cpp sample) and cornerSubPix over a ``half``-window. The sample's
    own 11 px reaches the next corner on left02 and right02 (22 and 19 px apart) and puts
    those views at 1.2 px RMS, moving fx by 3 px; 5 px keeps every view under 0.25 px."""
    import cv2

    out = []
    for n in names:
        img = cv2.imread(str(folder / n), cv2.IMREAD_GRAYSCALE)
        ok, c = cv2.findChessboardCorners(
            img, (9, 6), flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        assert ok, n
        out.append(cv2.cornerSubPix(img, c, (half, half), (-1, -1), (
            cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 0.01)))
    return out


def _stock(left: list, right: list, size: tuple[int, int]) -> np.ndarray:
    """Stock OpenCV on ``left``/``right`` corners: calibrateCamera for each camera, then
    stereoCalibrate with the intrinsics fixed (the CLI's own sequence). Returns
    fx, fy, cx, cy of left and of right, and the baseline (m)."""
    import cv2

    j = np.arange(54)
    obj = np.c_[j % 9, j // 9, np.zeros(54)].astype(np.float32) * 0.025
    objs = [obj] * len(left)
    _, K1, d1, _, _ = cv2.calibrateCamera(objs, left, size, None, None)
    _, K2, d2, _, _ = cv2.calibrateCamera(objs, right, size, None, None)
    out = cv2.stereoCalibrate(objs, left, right, K1, d1, K2, d2, size,
                              flags=cv2.CALIB_FIX_INTRINSIC)
    T = out[6]
    return np.r_[K1[0, 0], K1[1, 1], K1[0, 2], K1[1, 2], K2[0, 0], K2[1, 1], K2[0, 2],
                 K2[1, 2], np.linalg.norm(T)]


@pytest.fixture(scope="module")
def opencv_reference() -> dict:
    """Stock OpenCV on all 13 pairs of its sample, and its leave-one-pair-out spread: the
    largest change of each figure when one pair is left out (~2 s)."""
    import cv2

    names = sorted(p.name for p in SAMPLE.glob("left*.jpg"))
    left = _opencv_corners(SAMPLE, names)
    right = _opencv_corners(SAMPLE, [n.replace("left", "right") for n in names])
    size = cv2.imread(str(SAMPLE / names[0])).shape[1::-1]
    full = _stock(left, right, size)
    loo = np.array([_stock(left[:k] + left[k + 1:], right[:k] + right[k + 1:], size)
                    for k in range(len(names))])
    jack = np.sqrt((len(names) - 1) / len(names) * np.sum((loo - loo.mean(0)) ** 2, axis=0))
    return {"names": names, "full": full, "spread": np.abs(loo - full).max(axis=0),
            "jackknife": jack}


FIGURES = ["left fx", "left fy", "left cx", "left cy", "right fx", "right fy", "right cx",
           "right cy", "baseline"]


def _sample_folders(tmp_path: Path) -> tuple[Path, Path, Path]:
    """The sample's left and right images in folders of their own (a pair shares a name,
    as `calibrate stereo` wants), and the fields file."""
    lf, rf = tmp_path / "left", tmp_path / "right"
    lf.mkdir()
    rf.mkdir()
    for p in sorted(SAMPLE.glob("left*.jpg")):
        (lf / p.name.replace("left", "")).write_bytes(p.read_bytes())
        (rf / p.name.replace("left", "")).write_bytes(
            (SAMPLE / p.name.replace("left", "right")).read_bytes())
    fields = tmp_path / "sample.toml"
    fields.write_text(SAMPLE_FIELDS)
    return lf, rf, fields


def test_opencv_stereo_sample_calibrates_from_the_cli(opencv_reference, tmp_path, capsys):
    """Issue 34 done-when: OpenCV's own stereo chessboard sample (left01..14, right01..14,
    9 x 6 inner corners; 13 pairs) calibrates through `oralnav calibrate stereo` alone, and
    every figure (each camera's fx, fy, cx, cy and the baseline) lies within the data's
    own spread of stock OpenCV run on its own corners here (findChessboardCorners,
    cornerSubPix, calibrateCamera, stereoCalibrate): within the largest change
    leave-one-pair-out makes to OpenCV's figure. The per-view table lists all 13 views of
    each camera, any dropped ones with why, as JSON and as text (none is dropped: every
    view of this sample is under 0.25 px RMS with these corners)."""
    lf, rf, fields = _sample_folders(tmp_path)
    argv = ["calibrate", "stereo", "--left", str(lf), "--right", str(rf), "--fields",
            str(fields), "--board", "sample"]
    assert cli.run([*argv, "--json"]) == 0
    doc = _json(capsys)
    ours = []
    for cam in ("left", "right"):
        c = doc["intrinsics"][cam]
        K = np.array(c["K"])
        ours += [K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
        assert len(c["views"]) == 13 and all(r["file"].endswith(".jpg") for r in c["views"])
        for r in c["views"]:
            assert (r["status"] == "dropped") == (r["view"] in c["rejected"])
            if r["status"] == "dropped":
                assert r["why"].startswith(f"{r['rms_px']:.3f} px > limit")
    ours.append(doc["baseline_m"])
    ref = opencv_reference
    report = {f: (round(o, 4), round(r, 4), round(s, 4)) for f, o, r, s
              in zip(FIGURES, ours, ref["full"], ref["spread"], strict=True)}
    print("figure: (ours, OpenCV, leave-one-out spread)", report)
    print("dropped:", {c: [doc["intrinsics"][c]["views"][i]["file"]
                           for i in doc["intrinsics"][c]["rejected"]] for c in ("left", "right")},
          "stereo:", doc["rejected"])
    assert np.all(np.abs(np.array(ours) - ref["full"]) <= ref["spread"]), report
    assert len(doc["views"]) == 13 and doc["reject"] == "mad:4,median:2,floor:0.25"
    # the same in text: one row per image, the dropped ones marked with their reason
    assert cli.run(argv) == 0
    text = capsys.readouterr().out
    for cam in ("left", "right"):
        for i in doc["intrinsics"][cam]["rejected"]:
            name = doc["intrinsics"][cam]["views"][i]["file"]
            assert any(name in line and "dropped:" in line for line in text.splitlines())
    assert text.count("outlier rule mad:4,median:2,floor:0.25") == 3


def test_opencv_sample_one_camera_with_reject_none_is_stock_opencv(opencv_reference,
                                                                   tmp_path, capsys):
    """Issue 34 items 3-4: `oralnav calibrate camera` on the sample's left images alone;
    with --reject none every view is used and fx, fy, cx, cy lie within OpenCV's
    leave-one-out spread of stock OpenCV (the detectors differ, the solver does not);
    --min-views 14 is more than the 13 images and is refused (exit 2, nothing written);
    the file of an accepted fit records its outlier rule and view floor."""
    lf, _, fields = _sample_folders(tmp_path)
    base = ["calibrate", "camera", "--images", str(lf), "--fields", str(fields), "--board",
            "sample", "--json"]
    assert cli.run([*base, "--reject", "none"]) == 0
    doc = _json(capsys)
    assert doc["rejected"] == [] and len(doc["used"]) == 13 and doc["limit_px"] is None
    K = np.array(doc["K"])
    ours = np.r_[K[0, 0], K[1, 1], K[0, 2], K[1, 2]]
    ref = opencv_reference
    assert np.all(np.abs(ours - ref["full"][:4]) <= ref["spread"][:4]), (ours, ref["full"][:4])
    out = tmp_path / "cam.toml"
    assert cli.run([*base, "--min-views", "14", "--out", str(out), "--cell", "c"]) == 2
    assert "need at least 14" in _json(capsys)["error"] and not out.exists()
    assert cli.run([*base, "--reject", "none", "--min-views", "13", "--out", str(out),
                    "--cell", "c"]) == 0
    capsys.readouterr()
    quality = load_calibration(out, kind="camera").quality
    assert quality["outlier_rule"] == "none" and quality["min_views"] == 13
    assert "outlier_limit_px" not in quality and len(quality["used_views"]) == 13


@pytest.mark.parametrize("rule,reason", [("median", "not a term NAME:VALUE"),
                                         ("median:0.5", "expected a finite number >= 1")])
def test_bad_reject_rule_on_the_cli(tmp_path, capsys, rule, reason):
    """Issue 34 item 3 (bad input): a --reject rule that cannot be read exits 2 before
    any image is read, the message naming the rule."""
    code = cli.run(["calibrate", "camera", "--images", str(tmp_path / "none"), "--fields",
                    str(tmp_path / "none.toml"), "--reject", rule, "--json"])
    assert code == 2 and reason in _json(capsys)["error"]


@pytest.mark.parametrize("out, fmt", [("rig.xml", None), ("ros", "ros"),
                                      ("camchain.yaml", "kalibr")])
def test_rig_out_writes_the_ecosystems_formats(tmp_path, capsys, out, fmt):
    """Issue 34 item 2: `oralnav calibrate stereo --rig-out` writes OpenCV's FileStorage
    (from the suffix), a ROS camera_info pair (a folder) or a Kalibr camchain (of a
    `--model radtan` fit: Kalibr holds no k3), and the file loads back (``load_rig``, as
    `--rig` reads it) to the rig the calibration found."""
    from oralnav.config.rig import load_rig

    lf, rf, fields = _sample_folders(tmp_path)
    argv = ["calibrate", "stereo", "--left", str(lf), "--right", str(rf), "--fields",
            str(fields), "--board", "sample", "--rig-out", str(tmp_path / out), "--json"]
    extra = (["--rig-format", fmt] if fmt else []) + (["--model", "radtan"]
                                                      if fmt == "kalibr" else [])
    assert cli.run(argv + extra) == 0
    doc = _json(capsys)
    assert doc["rig_format"] == (fmt or "opencv")
    rig = load_rig(tmp_path / out)
    left, right = (rig[n] for n in rig.names)
    np.testing.assert_allclose(left.K, doc["intrinsics"]["left"]["K"], rtol=1e-9)
    np.testing.assert_allclose(right.K, doc["intrinsics"]["right"]["K"], rtol=1e-9)
    assert np.linalg.norm(right.T_ref_cam[:3, 3]) == pytest.approx(doc["baseline_m"], rel=1e-6)


def test_rig_out_of_an_unsaid_format_is_refused_before_calibrating(tmp_path, capsys):
    """Bad input: a .yaml --rig-out without --rig-format (OpenCV, ROS and Kalibr all write
    YAML) is refused at once, exit 2 naming the choices, and nothing is written."""
    lf, rf, fields = _sample_folders(tmp_path)
    code = cli.run(["calibrate", "stereo", "--left", str(lf), "--right", str(rf), "--fields",
                    str(fields), "--board", "sample", "--rig-out", str(tmp_path / "rig.yaml"),
                    "--out", str(tmp_path / "cal.toml"), "--cell", "c", "--json"])
    assert code == 2 and "--rig-format toml|opencv|ros|kalibr" in _json(capsys)["error"]
    assert not (tmp_path / "rig.yaml").exists() and not (tmp_path / "cal.toml").exists()
