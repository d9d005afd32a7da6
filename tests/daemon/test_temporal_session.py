"""The temporal calibration run by the daemon (issue 32, "Time"): the excitation through
the control loop, the record, the fit, on the virtual-clock cell whose frames arrive late,
stamped on arrival; what its offset does to a moving approach; and what refuses or
interrupts it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from oralnav.config.calibration import Calibration, SampleInfo
from oralnav.control.navigation.navigator import TwoStageNavigator
from oralnav.daemon.schemas import TemporalCalibrationBody
from oralnav.safety.errors import StateError
from tests.daemon.lockstep import SUPERVISE_EVERY, Lockstep, _config, start_procedure

#: 15 periods of 2 ms: the frames' stamps are 30 ms late
LATE = 15
#: the excitation of these tests: short, so the suite keeps its time
QUICK = TemporalCalibrationBody(amplitude_mm=4.0, period_s=2.0, duration_s=5.0)


async def _ready(c: Lockstep) -> None:
    await c.run(2 * c.camera_every + SUPERVISE_EVERY)  # poses, and READY
    c.core.supervise_once(c.clock.now())
    assert c.core.supervisor.state.value == "READY"


def _with_offset(offset_s: float):
    """config/sim.toml with a temporal calibration file of ``offset_s`` loaded."""
    cfg = _config()
    cal = Calibration(kind="temporal", cell="sim-cell", method="test", values={
        "offset_s": offset_s}, samples=SampleInfo(1, "0" * 64))
    return dataclasses.replace(cfg, calibrations={**cfg.calibrations, "temporal": cal})


async def test_recovers_an_injected_camera_offset_within_a_millisecond():
    """A camera whose stamps are 30 ms late: the daemon's excitation and fit find 30 ms
    within 1 ms (the issue's target), with an uncertainty that says so, and leave the
    cell READY with the arm back at rest; the navigation never steered the excitation."""
    c = Lockstep(latency_periods=LATE)
    await c.start()
    try:
        await _ready(c)
        doc = c.core.start_temporal(QUICK, "test")
        assert doc["phase"] == "moving"
        assert c.core.supervisor.state.value == "RUNNING"
        assert c.core.status()["safety"]["state"] == "RUNNING"
        assert c.core.status()["activity"] == "temporal calibration"
        s = c.core.temporal_session
        await c.run(int(6.5 / c.period), until=lambda: s.phase != "moving")
        s.wait(30)
        rep = c.core.temporal(samples=True)
        assert rep["phase"] == "done", rep["error"]
        res = rep["result"]
        assert abs(res["offset_s"] - LATE * c.period) < 1e-3, res
        assert res["sigma_s"] < 0.5e-3
        assert res["frames"] >= 40 and res["rejected"] == 0
        assert len(rep["samples"]["t_cam"]) == rep["frames"]
        assert rep["arm_samples"] > 5.0 / c.period  # the whole run, beyond the ring's 4 s
        assert c.core.supervisor.state.value == "READY"
        assert c.core.status()["activity"] is None
        assert c.nav.navigator is None
        moved = np.ptp(np.array(rep["samples"]["p_B"]), axis=0)
        assert 4e-3 < moved.max() < 9e-3  # the excitation's +-4 mm, no more
    finally:
        await c.close()


async def _approach(latency_periods: int, cfg=None) -> list[tuple[float, float]]:
    """One extra-oral approach on the virtual-clock cell: for every goal computed while
    approaching, (aim error mm, true TCP speed mm/s). The aim error: where the goal would
    put the end-effector zero frame against the true entry pose (the cell's truth)."""
    c = Lockstep(latency_periods=latency_periods, cfg=cfg)
    geo = c.cfg.cell.geometry
    out: list[tuple[float, float]] = []
    last: list[tuple[float, np.ndarray]] = []
    update = TwoStageNavigator.update

    def spy(nav, T_C_RM, T_C_OM, T_En_EM, T_B_tcp):
        stage = nav.stage
        step = update(nav, T_C_RM, T_C_OM, T_En_EM, T_B_tcp)
        truth = c.cell.truth()
        if stage == "approach" and step.goal is not None:
            aim = (step.goal @ geo.T_tcp_E0)[:3, 3] - (truth["T_B_OM"] @ nav.T_OM_E0_entry)[:3, 3]
            p, t = truth["T_B_tcp"][:3, 3], truth["time"]
            speed = np.linalg.norm(p - last[-1][1]) / (t - last[-1][0]) if last else 0.0
            last.append((t, p))
            out.append((float(np.linalg.norm(aim)) * 1e3, float(speed) * 1e3))
        return step

    await c.start()
    try:
        TwoStageNavigator.update = spy
        await start_procedure(c)
        await c.run(int(30 / c.period), until=lambda: c.nav.navigator is not None
                    and c.nav.navigator.stage != "approach")
        assert c.nav.navigator.stage == "adjust", c.core.supervisor.reasons
    finally:
        TwoStageNavigator.update = update
        await c.close()
    return out


@pytest.mark.slow
async def test_the_offset_applied_brings_a_moving_approach_back_to_the_static_figure():
    """Frames 30 ms late, the approach's goals are aimed wrong by speed x 30 ms while the
    arm moves; with the temporal calibration's offset applied they are back at the
    figure of a camera with no delay. The figures (the issue asks for them) are printed."""
    runs = {"no delay": await _approach(0),
            "30 ms late, not corrected": await _approach(LATE),
            "30 ms late, corrected": await _approach(LATE, _with_offset(LATE * 2e-3))}
    fig = {}
    for name, rows in runs.items():
        moving = np.array([a for a, v in rows if v > 5.0])
        assert len(moving) >= 5, name
        fig[name] = (float(np.mean(moving)), float(np.max(moving)), len(moving))
        print(f"moving approach, {name}: aim error mean {fig[name][0]:.3f} mm, max "
              f"{fig[name][1]:.3f} mm over {fig[name][2]} frames above 5 mm/s")
    static, late, fixed = (fig[k][0] for k in runs)
    assert late > 2 * static + 0.1       # speed x 30 ms shows
    assert fixed < 1.5 * static + 0.02   # and is gone


async def test_refused_unless_ready_with_the_robot_marker_in_view():
    """Nothing moves when the run cannot start: before READY, during a procedure, with
    the robot marker out of view, or with an excitation too short to fit; each 409
    names why."""
    c = Lockstep()
    await c.start()
    try:
        with pytest.raises(StateError, match="READY"):
            c.core.start_temporal(QUICK, "test")
        await c.run(2 * SUPERVISE_EVERY, frozen=lambda: True)  # READY, no frame seen yet
        assert c.core.supervisor.state.value == "READY"
        with pytest.raises(StateError, match="robot marker"):
            c.core.start_temporal(QUICK, "test")
        await _ready(c)
        with pytest.raises(StateError, match="two periods|2 periods"):
            c.core.start_temporal(TemporalCalibrationBody(period_s=4.0, duration_s=6.0),
                                  "test")
        assert c.core.temporal()["phase"] == "idle"
        assert int(c.control.read_status()["motion_commands"]) == 0
    finally:
        await c.close()
    c = Lockstep()
    await c.start()
    try:
        await start_procedure(c)
        with pytest.raises(StateError, match="RUNNING"):
            c.core.start_temporal(QUICK, "test")
    finally:
        await c.close()


async def test_a_stop_mid_excitation_fails_the_run_and_leaves_nothing_to_resume():
    """An e-stop during the excitation: the run ends as failed naming the state, the arm
    holds, and after the reset no interrupted activity can be resumed (the next start of
    the procedure is allowed)."""
    c = Lockstep()
    await c.start()
    try:
        await _ready(c)
        c.core.start_temporal(QUICK, "test")
        await c.run(int(1.0 / c.period))
        c.core.estop("test", "operator pressed")
        await c.run(SUPERVISE_EVERY)
        rep = c.core.temporal()
        assert rep["phase"] == "failed" and "ESTOP" in rep["error"]
        assert c.core.supervisor.interrupted is None
        c.core.reset("test")
        await c.run(2 * c.camera_every)
        c.core.supervise_once(c.clock.now())
        assert c.core.supervisor.state.value == "READY"
        await start_procedure(c)
        assert c.core.activity == "procedure"
    finally:
        await c.close()


async def test_the_calibrated_offset_is_subtracted_from_the_stereo_stamps_only():
    """With a temporal calibration of 10 ms the stereo poses are published 10 ms before
    their frames' stamps; the endoscope's, which it does not calibrate, are not moved."""
    c = Lockstep(cfg=_with_offset(0.010))
    await c.start()
    try:
        await c.run(c.camera_every)
        t = c.cell.truth()["time"]
        assert c.core.pose("T_C_RM")["stamp"] == pytest.approx(t - 0.010, abs=1e-12)
        assert c.core.pose("T_C_OM")["stamp"] == pytest.approx(t - 0.010, abs=1e-12)
        en = c.core.pose("T_En_EM")
        assert en is None or en["stamp"] == t
        assert c.core.temporal_session.applied_offset == 0.010
    finally:
        await c.close()


def test_the_configuration_names_the_offset_or_warns_and_takes_zero(tmp_path, caplog):
    """[calibration] temporal loads a 'temporal' file (seconds, whatever its length unit)
    and the stereo source applies it; without one the daemon warns, naming the command,
    and takes 0: motion is bounded per frame (docs/calibration.md says why a missing
    offset is no refusal)."""
    from oralnav.config.calibration import save_calibration
    from oralnav.config.daemon import load_config
    from oralnav.daemon.capture_task import stereo_offset
    from tests.daemon.test_navigation_task import _hardware_config

    save_calibration(Calibration(kind="temporal", cell="c1", method="test",
                                 values={"offset_s": 0.0234},
                                 samples=SampleInfo(50, "0" * 64)), tmp_path / "t.toml")
    text = (tmp_path / "t.toml").read_text().replace('length = "m"', 'length = "mm"')
    (tmp_path / "t.toml").write_text(text)
    cfg = load_config(_hardware_config(
        tmp_path, f'[calibration]\ncell = "c1"\ntemporal = "{tmp_path / "t.toml"}"\n'))
    assert stereo_offset(cfg) == 0.0234
    with caplog.at_level("WARNING"):
        assert stereo_offset(load_config(_hardware_config(tmp_path))) == 0.0
    assert "oralnav calibrate temporal" in caplog.text
