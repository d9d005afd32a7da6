"""Position-based visual servoing of a held needle (issue 36, item 1): the law and its
guards, free of I/O and of time sources (the caller passes the clock).

The needle held in closed jaws moves with the true tool, and the arm is commanded through
its *reported* tool pose, which differs from the true one by the arm's kinematic error
(``reported = E @ true``: joint offsets, registration). A motion planned open-loop puts
the needle where the plan says only when ``E`` is the identity: with ``E`` a rotation of
0.5 deg about the arm's RCM and a 1 mm shift, 60 % of the simulated trials failed,
mostly in the drive (``oralnav bench needle --arm-error 1 0.5``, docs/needle.md). The
servo corrects from where the needle is *seen*: each tracked pose gives the error of a
control point on the needle (the tip during a drive) and of the needle's orientation,
and the command moves the reported tool by a share of that error, rotating about the
control point. The commanded change reaches the true tool turned by ``E``'s rotation, so
the updates contract while that rotation is small (a few degrees), whatever ``E``'s
shift; the servo never needs ``E`` itself.

Position-based rather than image-based: the tracker already fuses both views into a pose
with its uncertainty (the refinement's sigmas), the goals are poses (the drive's arc,
the hand-off pose), and a pose error turns into a tool motion without an image Jacobian
per view; an image-based law would have to rebuild what the refinement does.

Guards, each a :class:`ServoStop` naming its cause, before anything is commanded:

- ``lost``: the tracker has not converged on the frame (its reason is carried);
- ``uncertain``: the pose's one-sigma position or angle over the servo's bounds;
- ``stale``: the frame older than ``max_age`` at the time of the update;
- ``jump``: the seen pose off where the last seen pose, moved as the tool moved since,
  puts it, by more than ``max_jump_shift`` or ``max_jump_turn`` (a twin flip turns the
  needle 180 deg; a slip in the jaws moves it); never a servo on a contradicted pose;
- ``not_finite``: a pose that is not a finite rigid transform;
- ``no_progress``: ``max_updates`` corrections without reaching the goal;
- ``implausible`` (:class:`DriveServo`): the needle seen further off the plan than the
  arms' stated accuracy allows: the tracker's error, not the arm's.

A frame no newer than the last one used is not used twice (that would double its
correction): the update holds (an identity command). Frames: the reference frame (the
stereo endoscope's left channel); metres, radians; stamps in seconds of the caller's
monotonic clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from oralnav.control.errors import GeometryError, NeedleError
from oralnav.control.geometry import as_transform, rotation_angle

__all__ = ["DriveServo", "HeldNeedleServo", "Seen", "ServoCommand", "ServoSettings", "ServoStop"]


@dataclass(frozen=True)
class ServoSettings:
    """``gain``: the share of the seen error corrected per update, in (0, 1]; each
    correction at most ``max_shift`` (m, of the control point) and ``max_turn`` (rad),
    scaled together so the correction keeps the error's direction; the goal is reached
    within ``done_shift`` (m) and ``done_turn`` (rad). The guards' bounds: ``max_age``
    (s), ``max_sigma_position`` (m) and ``max_sigma_angle`` (rad) (the tracker's own
    convergence bounds by default), ``max_jump_shift`` (m) and ``max_jump_turn`` (rad),
    ``max_updates``."""

    gain: float = 0.6
    max_shift: float = 0.001
    max_turn: float = math.radians(2.0)
    done_shift: float = 0.0001
    done_turn: float = math.radians(0.2)
    max_age: float = 0.1
    max_sigma_position: float = 0.0003
    max_sigma_angle: float = math.radians(1.5)
    max_jump_shift: float = 0.002
    max_jump_turn: float = math.radians(10.0)
    max_updates: int = 50

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gain) and 0.0 < self.gain <= 1.0):
            raise NeedleError(f"servo: gain must be in (0, 1], got {self.gain}")
        for name in ("max_shift", "max_turn", "done_shift", "done_turn", "max_age",
                     "max_sigma_position", "max_sigma_angle", "max_jump_shift",
                     "max_jump_turn"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise NeedleError(f"servo: {name} must be finite and > 0, got {v}")
        if isinstance(self.max_updates, bool) or not isinstance(self.max_updates, int) \
                or self.max_updates < 1:
            raise NeedleError(f"servo: max_updates must be an integer >= 1, got "
                              f"{self.max_updates!r}")


@dataclass(frozen=True)
class Seen:
    """One tracked frame: the needle's pose ``T_ref_N`` (4x4, m), the frame's capture
    ``stamp`` (s), whether the tracker ``converged`` on it (``reason`` when not), the
    pose's one-sigma ``sigma_position`` (m) and ``sigma_angle`` (rad), and whether the
    fit found too little of the arc while matching what it found (``short``:
    ``NeedleTrack.short``)."""

    pose: np.ndarray
    stamp: float
    converged: bool = True
    reason: str = ""
    sigma_position: float = 0.0
    sigma_angle: float = 0.0
    short: bool = False

    @classmethod
    def from_track(cls, track, stamp: float, held: bool = False) -> Seen:
        """From a :class:`~oralnav.control.needle.tracker.NeedleTrack` and its frame's
        capture time (s); a track without a refinement has no sigmas (infinite).
        ``held``: the needle is in closed jaws, which fix its slide along its own circle:
        the track is judged as the tracker judges a held needle (``held_reason``), and
        ``sigma_angle`` is that of the needle's plane (``Refined.sigma_tilt``), for
        :class:`DriveServo`, which servoes the circle alone."""
        r = track.refined
        reason = track.held_reason if held else track.reason
        angle = math.inf if r is None else float(r.sigma_tilt if held else r.sigma_angle)
        return cls(np.asarray(track.pose, dtype=float), float(stamp), not reason, reason,
                   math.inf if r is None else float(r.sigma_position), angle,
                   bool(track.short))


class ServoStop(NeedleError):
    """The servo will not command a motion: ``cause`` (``lost``, ``uncertain``,
    ``stale``, ``jump``, ``not_finite``, ``no_progress``) and what it saw."""

    def __init__(self, cause: str, detail: str) -> None:
        super().__init__(f"servo stopped ({cause}): {detail}")
        self.cause = cause
        self.detail = detail


@dataclass(frozen=True)
class ServoCommand:
    """One update's answer: move the reported tool to ``delta @`` its current pose
    (``delta`` 4x4, reference frame; the identity when ``done`` or holding); ``shift``
    (m) and ``turn`` (rad): the seen error of the control point and the orientation;
    ``done``: the goal is reached; ``held``: the frame was not newer than the last one
    used, nothing was corrected."""

    delta: np.ndarray
    shift: float
    turn: float
    done: bool
    held: bool = False


def _transform(T: np.ndarray, what: str) -> np.ndarray:
    """``T`` as a rigid 4x4 (:func:`~oralnav.control.geometry.as_transform`), or a
    ``not_finite`` :class:`ServoStop` naming what is wrong with ``what``."""
    try:
        return as_transform(T, what=what)
    except GeometryError as exc:
        raise ServoStop("not_finite", str(exc)) from None


def _check_frame(seen: Seen) -> None:
    """The guards every servo puts a frame through first: a finite rigid pose and stamp
    (``not_finite``)."""
    _transform(seen.pose, "the tracked pose")
    if not math.isfinite(seen.stamp):
        raise ServoStop("not_finite", f"the frame's stamp is {seen.stamp}")


def _check_age(seen: Seen, now: float, s: ServoSettings) -> None:
    """``stale``: the frame older than ``max_age`` at time ``now`` (s)."""
    age = now - seen.stamp
    if age > s.max_age:
        raise ServoStop("stale", f"the frame is {age * 1e3:.0f} ms old (bound "
                                 f"{s.max_age * 1e3:.0f} ms)")


def _about(point: np.ndarray, rotvec: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """The rigid motion that turns by ``rotvec`` (rad) about ``point`` (m), then shifts
    by ``shift`` (m); 4x4."""
    R = Rotation.from_rotvec(rotvec).as_matrix()
    D = np.eye(4)
    D[:3, :3] = R
    D[:3, 3] = point - R @ point + shift
    return D


class HeldNeedleServo:
    """Servo a held needle to ``goal`` (``T_ref_N``, 4x4, m): the error measured at
    ``control_point`` (3,, needle frame, m; the tip during a drive) and in orientation.
    Call :meth:`update` with each new tracked frame; move the reported tool by each
    command's ``delta`` until it says ``done``; a :class:`ServoStop` means stop the arm."""

    def __init__(self, goal: np.ndarray, control_point: np.ndarray | None = None,
                 settings: ServoSettings | None = None) -> None:
        self.goal = _transform(goal, "the goal").copy()
        cp = np.zeros(3) if control_point is None else np.asarray(control_point, float)
        if cp.shape != (3,) or not np.all(np.isfinite(cp)):
            raise NeedleError(f"servo: the control point must be 3 finite values (m), got "
                              f"{control_point!r}")
        self.control_point = cp
        self.s = settings or ServoSettings()
        self.updates = 0
        self._last: Seen | None = None
        self._last_delta = np.eye(4)

    def _point(self, T: np.ndarray) -> np.ndarray:
        return T[:3, :3] @ self.control_point + T[:3, 3]

    def _check(self, seen: Seen, now: float, tool_motion: np.ndarray | None) -> None:
        s = self.s
        _check_frame(seen)
        if not seen.converged:
            raise ServoStop("lost", f"the tracker has not converged ({seen.reason})")
        if seen.sigma_position > s.max_sigma_position or seen.sigma_angle > s.max_sigma_angle:
            raise ServoStop("uncertain", f"the pose is uncertain ({seen.sigma_position * 1e3:.2f}"
                                         f" mm, {math.degrees(seen.sigma_angle):.2f} deg; "
                                         f"bounds {s.max_sigma_position * 1e3:.2f} mm, "
                                         f"{math.degrees(s.max_sigma_angle):.2f} deg)")
        _check_age(seen, now, s)
        if self._last is not None:
            motion = (self._last_delta if tool_motion is None
                      else _transform(tool_motion, "the tool's motion"))
            predicted = motion @ self._last.pose
            off = float(np.linalg.norm(self._point(seen.pose) - self._point(predicted)))
            turn = rotation_angle(seen.pose[:3, :3], predicted[:3, :3])
            if off > s.max_jump_shift or turn > s.max_jump_turn:
                raise ServoStop("jump", f"the needle is seen {off * 1e3:.2f} mm and "
                                        f"{math.degrees(turn):.1f} deg from where the tool's "
                                        f"motion puts it (bounds {s.max_jump_shift * 1e3:.1f} "
                                        f"mm, {math.degrees(s.max_jump_turn):.0f} deg)")

    def update(self, seen: Seen, now: float,
               tool_motion: np.ndarray | None = None) -> ServoCommand:
        """The command for the tracked frame ``seen`` at time ``now`` (s, the stamps'
        clock). ``tool_motion``: how the reported tool moved (4x4, reference frame, left
        factor) between the last frame used and this one; by default the last command's
        delta (the motion completed before the frame was taken). :class:`ServoStop` when
        a guard trips."""
        if self._last is not None and seen.stamp <= self._last.stamp:
            return ServoCommand(np.eye(4), math.nan, math.nan, done=False, held=True)
        self._check(seen, now, tool_motion)
        T = np.asarray(seen.pose, dtype=float)
        p = self._point(T)
        e_p = self._point(self.goal) - p
        w = Rotation.from_matrix(self.goal[:3, :3] @ T[:3, :3].T).as_rotvec()
        shift, turn = float(np.linalg.norm(e_p)), float(np.linalg.norm(w))
        self._last = seen
        if shift <= self.s.done_shift and turn <= self.s.done_turn:
            self._last_delta = np.eye(4)
            return ServoCommand(np.eye(4), shift, turn, done=True)
        self.updates += 1
        if self.updates > self.s.max_updates:
            raise ServoStop("no_progress", f"{self.s.max_updates} corrections and the "
                                           f"needle is still {shift * 1e3:.2f} mm and "
                                           f"{math.degrees(turn):.2f} deg from the goal")
        k = min(self.s.gain, self.s.max_shift / shift if shift > 0 else math.inf,
                self.s.max_turn / turn if turn > 0 else math.inf)
        delta = _about(p, k * w, k * e_p)
        self._last_delta = delta
        return ServoCommand(delta, shift, turn, done=False)


def _moved_by(applied: np.ndarray, point: np.ndarray) -> np.ndarray:
    """How far (m, reference frame) rigid motion ``applied`` (4x4) moves ``point`` (3,)."""
    return applied[:3, :3] @ point + applied[:3, 3] - point


def _plane_turn(seen: np.ndarray, goal: np.ndarray) -> np.ndarray:
    """The shortest rotation vector (rad, reference frame) that turns the needle plane's
    normal (N's z) of rotation ``seen`` onto that of ``goal`` (3x3 each): the circle's
    orientation error, without the slide along it."""
    a, b = seen[:, 2], goal[:, 2]
    axis = np.cross(a, b)
    sin = float(np.linalg.norm(axis))
    return np.zeros(3) if sin < 1e-12 else axis * (math.atan2(sin, float(a @ b)) / sin)


class DriveServo:
    """Servo a held needle's circle along a drive: the needle's planned poses ``goals``
    (n, 4, 4; ``T_ref_N``, m), each the first turned about the needle's own axis through
    its centre, which the plan holds still.

    Why the circle alone: once the tip is under the tissue and the swage in the jaws, the
    views cannot see the needle slide along itself, which the jaws fix anyway; where the
    bite enters and leaves depends on the circle (centre and plane) alone. The tracked
    centre is good to about 0.1 mm while enough of the arc shows.

    Why a model, not only a gain on the last error: the arm's kinematic error ``E`` and
    the error it left in the seen grasp make the true centre wander as the tool turns:
    seen at drive pose ``k``, the centre is off the plan by ``m_k = d_k - e + A_k x``
    (first order in ``E``): ``d_k`` the translation the servo has added at pose ``k``,
    ``e`` the arm's error at the centre (reference frame), ``A_k`` pose ``k``'s planned
    rotation and ``x`` the grasp's error (needle frame, m). Each usable look adds three
    equations; ``e`` and ``x`` are the least-squares solution with a zero-mean prior of
    ``prior_shift`` (m, one sigma) on each, weighed against the look's own
    ``sigma_position``, so one look only shifts the circle and the rotation-dependent part
    is learnt as the turn grows. :meth:`correction` then predicts, for every later pose,
    the translation that puts the centre on the plan, which carries the drive on where the
    views lose the centre (half the arc under the tissue, the rest near the jaws).

    Guards (each a :class:`ServoStop`): ``not_finite``; ``uncertain``: the views show too
    little of the arc (``Seen.short``: the fit matches what it finds, the jaws and the
    tissue hide the rest), or the centre's or the plane's sigma is over the settings'
    bounds: a look not to move on, which contradicts nothing (the caller carries on on
    the model's prediction); ``lost``: the tracker not converged for another reason (off
    the wire, a fit that does not match, base and tip in doubt): stop; ``stale``; ``jump``:
    the centre or the plane off where the last usable look, moved as the tool moved since,
    puts it (a slip in the jaws, a twin): stop. Units: metres, radians, seconds.
    """

    def __init__(self, goals: np.ndarray, settings: ServoSettings | None = None,
                 prior_shift: float = 0.003, plausible_sigmas: float = 4.0) -> None:
        goals = np.asarray(goals, dtype=float)
        if goals.ndim != 3 or goals.shape[1:] != (4, 4) or len(goals) < 1:
            raise NeedleError(f"drive servo: the goals must be (n, 4, 4) poses, got "
                              f"{goals.shape}")
        self.goals = np.stack([_transform(g, f"drive goal {k + 1}")
                               for k, g in enumerate(goals)])
        if not (math.isfinite(prior_shift) and prior_shift > 0):
            raise NeedleError(f"drive servo: prior_shift must be finite and > 0 m, got "
                              f"{prior_shift}")
        if not (math.isfinite(plausible_sigmas) and plausible_sigmas > 0):
            raise NeedleError(f"drive servo: plausible_sigmas must be finite and > 0, got "
                              f"{plausible_sigmas}")
        self.s = settings or ServoSettings()
        self.prior_shift = float(prior_shift)
        self.plausible_sigmas = float(plausible_sigmas)
        self._rows: list[np.ndarray] = []
        self._rhs: list[np.ndarray] = []
        self._weights: list[float] = []
        self._angles: list[float] = []
        self._theta = np.zeros(6)          # (e, x)
        self._last: Seen | None = None

    @property
    def looks(self) -> int:
        """How many looks the model has."""
        return len(self._weights)

    @property
    def span(self) -> float:
        """The drive's turn (rad) between the model's first and last look: how much of
        the rotation-dependent error it has seen."""
        return max(self._angles) - min(self._angles) if self._angles else 0.0

    def _angle(self, k: int) -> float:
        """How far (rad) goal ``k`` is turned from the first about the needle's axis."""
        R = self.goals[0][:3, :3].T @ self.goals[k][:3, :3]
        return abs(math.atan2(R[1, 0], R[0, 0]))

    def correction(self, k: int) -> np.ndarray:
        """The translation (4x4, reference frame) that puts the centre on the plan at
        drive pose ``k``, as the model predicts (the identity before any look)."""
        e, x = self._theta[:3], self._theta[3:]
        D = np.eye(4)
        D[:3, 3] = e - self.goals[k][:3, :3] @ x
        return D

    def predicted(self, k: int, applied: np.ndarray) -> np.ndarray:
        """Where the model puts the needle (``T_ref_N``, 4x4) at drive pose ``k`` with the
        arm sent ``applied`` (4x4, reference frame) times the planned pose there: the
        goal, its centre moved by ``d_k - e + A_k x``. Its change between two looks is the
        needle's motion as the arm truly makes it, the tracker's prior (the reported
        motion would carry the corrections, which the model says cancel the wander)."""
        goal = self.goals[k]
        c = goal[:3, 3]
        T = goal.copy()
        T[:3, 3] = c + _moved_by(applied, c) - self._theta[:3] + goal[:3, :3] @ self._theta[3:]
        return T

    def check(self, seen: Seen, now: float, tool_motion: np.ndarray) -> None:
        """The guards on ``seen`` at time ``now`` (s), the reported tool having moved by
        ``tool_motion`` (4x4, reference frame, left factor) since the last usable look;
        a :class:`ServoStop` when one trips."""
        s = self.s
        _check_frame(seen)
        if seen.short and not seen.converged:
            raise ServoStop("uncertain", f"the views show too little of the arc "
                                         f"({seen.reason})")
        if seen.sigma_position > s.max_sigma_position or seen.sigma_angle > s.max_sigma_angle:
            raise ServoStop("uncertain", f"the circle is uncertain ({seen.sigma_position * 1e3:.2f}"
                                         f" mm, plane {math.degrees(seen.sigma_angle):.2f} deg;"
                                         f" bounds {s.max_sigma_position * 1e3:.2f} mm, "
                                         f"{math.degrees(s.max_sigma_angle):.2f} deg)")
        if not seen.converged:
            raise ServoStop("lost", f"the tracker has not converged ({seen.reason})")
        _check_age(seen, now, s)
        if self._last is not None:
            predicted = _transform(tool_motion, "the tool's motion") @ self._last.pose
            off = float(np.linalg.norm(seen.pose[:3, 3] - predicted[:3, 3]))
            turn = float(np.linalg.norm(_plane_turn(seen.pose[:3, :3], predicted[:3, :3])))
            if off > s.max_jump_shift or turn > s.max_jump_turn:
                raise ServoStop("jump", f"the needle's circle is seen {off * 1e3:.2f} mm and "
                                        f"{math.degrees(turn):.1f} deg from where the tool's "
                                        f"motion puts it (bounds {s.max_jump_shift * 1e3:.1f} "
                                        f"mm, {math.degrees(s.max_jump_turn):.0f} deg)")

    def update(self, k: int, seen: Seen, now: float, tool_motion: np.ndarray,
               applied: np.ndarray, weight: float = 1.0) -> float:
        """Take the look ``seen`` at drive pose ``k`` (after :meth:`check`'s guards, which
        raise), the arm having been sent ``applied`` (4x4, reference frame) times the
        planned pose there; refit the model. ``weight`` (0, 1]: the look's share of an
        independent look's weight (frames a few poses apart share their errors: the same
        views, the same biases). Returns how far (m) the centre was seen from the plan.

        ``implausible`` (a :class:`ServoStop`): the centre, less the servo's own
        translation, further from the plan than ``plausible_sigmas`` times what the
        model's prior allows (the arm's error and the grasp's, ``prior_shift`` each) and
        the look's own sigma: what the arms cannot have done, the tracker did (an
        exact-armed validation trial, 1000607, saw 13 mm at the approach and drove 3 mm
        off)."""
        self.check(seen, now, tool_motion)
        if not (math.isfinite(weight) and 0.0 < weight <= 1.0):
            raise NeedleError(f"drive servo: a look's weight must be in (0, 1], got {weight}")
        goal = self.goals[k]
        m = seen.pose[:3, 3] - goal[:3, 3]
        d = _moved_by(applied, goal[:3, 3])
        off = float(np.linalg.norm(m - d))
        bound = self.plausible_sigmas * math.hypot(math.sqrt(2.0) * self.prior_shift,
                                                   seen.sigma_position)
        if off > bound:
            raise ServoStop("implausible", f"the centre is seen {off * 1e3:.2f} mm from where "
                                           f"the plan and the servo put it; the arms' stated "
                                           f"accuracy allows {bound * 1e3:.2f} mm")
        # m - d = -e + A_k x
        self._rows.append(np.hstack([-np.eye(3), goal[:3, :3]]))
        self._rhs.append(m - d)
        self._weights.append(weight / max(seen.sigma_position, 1e-5))
        self._angles.append(self._angle(k))
        self._last = seen
        W = np.repeat(self._weights, 3)
        A = np.vstack(self._rows) * W[:, None]
        b = np.concatenate(self._rhs) * W
        # the prior: each unknown zero, one sigma prior_shift
        A = np.vstack([A, np.eye(6) / self.prior_shift])
        b = np.concatenate([b, np.zeros(6)])
        self._theta = np.linalg.lstsq(A, b, rcond=None)[0]
        return float(np.linalg.norm(m))
