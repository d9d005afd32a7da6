"""Pose helpers of the needle procedure (4x4 transforms, m, rad): a translation, a
gripper's back-off along its own axis, a turn about a line, and the straight-line, slerp
path a cell's arm moves along."""

from __future__ import annotations

import math

import cv2
import numpy as np

from oralnav.control.geometry import make_transform
from oralnav.control.motion import geodesic, rotation_log


def translation(v: np.ndarray) -> np.ndarray:
    """The 4x4 transform that moves points by ``v`` (3,, m) without turning them."""
    return make_transform(t=np.asarray(v, dtype=float))


def back_off(T: np.ndarray, d: float, tilt: float = 0.0) -> np.ndarray:
    """``T`` moved ``d`` (m) along its own -z (out of the jaws' way), or along -z turned
    by ``tilt`` (rad) about its y: still in the plane of the jaws' faces, so open jaws
    slide off a wire that lies across them without dragging it (the wire runs along x,
    the jaws close along y)."""
    return T @ make_transform(t=[-d * math.sin(tilt), 0.0, -d * math.cos(tilt)])


#: Directions an opened gripper may back off the wire by (rad about its y, from -z):
#: straight first, then ever more aslant, up to 60 deg (the jaws still clear the wire).
_BACK_OFF_TILTS = tuple(math.radians(a) for a in (0, 20, -20, 40, -40, 60, -60))


def turn_about(axis: np.ndarray, angle: float, point: np.ndarray) -> np.ndarray:
    """A rotation by ``angle`` about the line through ``point`` along ``axis`` (4x4)."""
    a = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    R, _ = cv2.Rodrigues(a * angle)
    T = make_transform(R)
    T[:3, 3] = point - R @ point
    return T


#: A checked path's spacing (m, rad): the simulated cell's motion increments, so that a
#: long turn is checked where the cell will check it (a wrist limit crossed between two
#: samples 20 deg apart stops the motion half-way).
_PATH_STEP = 0.001
_PATH_TURN = math.radians(2.0)


def _path(T0: np.ndarray, T1: np.ndarray, n: int | None = None) -> list[np.ndarray]:
    """``n`` poses along the straight-line, slerp path from ``T0`` to ``T1`` (the cell's
    motion), ``T1`` last: a goal the arm reaches by a path it cannot follow is no goal.
    By default at least 8, and one per ``_PATH_STEP`` and per ``_PATH_TURN``."""
    if n is None:
        turn = float(np.linalg.norm(rotation_log(T0[:3, :3].T @ T1[:3, :3])))
        dist = float(np.linalg.norm(T1[:3, 3] - T0[:3, 3]))
        # the cell's own rounding of its increments: a turn of an exact number of
        # increments (the hand-off's and the show pose's turns are multiples of 30 deg)
        # is checked at the cell's poses, not one more or less by the last bit
        n = max(8, math.ceil(dist / _PATH_STEP - 1e-9), math.ceil(turn / _PATH_TURN - 1e-9))
    f = np.arange(1, n + 1) / n
    T = np.zeros((n, 4, 4))
    T[:, :3, :3] = geodesic(T0[:3, :3], T1[:3, :3], f)
    T[:, :3, 3] = T0[:3, 3] + f[:, None] * (T1[:3, 3] - T0[:3, 3])
    T[:, 3, 3] = 1.0
    return list(T)
