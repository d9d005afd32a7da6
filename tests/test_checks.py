"""Tests of oralnav/checks.py, the argument checks every layer shares (issue 31)."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from oralnav.checks import (
    ROTATION_TOL,
    NumberMessages,
    TransformMessages,
    finite_array,
    finite_number,
    positive_number,
    rigid_transform,
)


class Refused(ValueError):
    """The error class the tests hand to the checks."""


def _pose() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    T[:3, 3] = [0.1, -0.05, 0.3]
    return T


# -- rigid_transform ---------------------------------------------------------------------


def test_rigid_transform_accepts_a_pose_and_copies_only_when_asked():
    """issue 31 shared argument checks: a rigid transform comes back as a float 4x4, the
    same array unless ``copy``; a list converts; the bottom row is kept as given."""
    T = _pose()
    assert rigid_transform(T, "T", Refused) is T
    out = rigid_transform(T, "T", Refused, copy=True)
    assert out is not T and np.array_equal(out, T)
    out[0, 3] = 9.0
    assert T[0, 3] == 0.1
    listed = rigid_transform(T.tolist(), "T", Refused)
    assert listed.dtype == float and np.array_equal(listed, T)
    T[3, 3] = 1.0 + 0.5 * ROTATION_TOL
    assert rigid_transform(T, "T", Refused)[3, 3] == T[3, 3]


@pytest.mark.parametrize("bad, message", [
    ("abc", r"^T must be a 4x4 transform, got 'abc'$"),
    ([[1.0, 2.0], [3.0]], r"^T must be a 4x4 transform, got \[\[1\.0, 2\.0\], \[3\.0\]\]$"),
    (np.eye(3), r"^T must be a 4x4 transform, got shape \(3, 3\)$"),
    (np.where(np.eye(4) == 1, np.nan, 0.0), r"^T has non-finite entries$"),
    (np.vstack([np.eye(4)[:3], [0.0, 0.0, 0.1, 1.0]]),
     r"^T bottom row must be \[0, 0, 0, 1\], got \[0\.0, 0\.0, 0\.1, 1\.0\]$"),
    (np.diag([1.0, 1.0, -1.0, 1.0]),
     r"^T rotation block is not a rotation \(\|R\^T R - I\| = 0\.00e\+00, det = -1\.000\)$"),
    (np.diag([1.0, 1.0, 1.001, 1.0]),
     r"^T rotation block is not a rotation \(\|R\^T R - I\| = 2\.00e-03, det = 1\.001\)$"),
])
def test_rigid_transform_refusals_in_the_default_wording(bad, message):
    """issue 31 shared argument checks: each malformed transform raises the error class
    given, with the default wording (safety's) naming what is wrong."""
    with pytest.raises(Refused, match=message):
        rigid_transform(bad, "T", Refused)


def test_rigid_transform_tolerances():
    """issue 31 shared argument checks: ``tol`` bounds ``|R^T R - I|`` and the bottom row;
    ``det_tol`` also bounds ``|det - 1|`` (a block scaled by 1 + 4e-7 is orthonormal within
    1e-6, but its determinant is 1.2e-6 off)."""
    T = _pose()
    T[:3, :3] *= 1.0 + 4e-7
    assert rigid_transform(T, "T", Refused, tol=1e-6) is T
    with pytest.raises(Refused, match="det = 1.000"):
        rigid_transform(T, "T", Refused, tol=1e-6, det_tol=1e-6)
    assert rigid_transform(T, "T", Refused, tol=1e-6, det_tol=1e-5) is T
    with pytest.raises(Refused, match="not a rotation"):
        rigid_transform(T, "T", Refused, tol=1e-7)
    T = _pose()
    T[3, 0] = 1e-5
    with pytest.raises(Refused, match="bottom row"):
        rigid_transform(T, "T", Refused)
    assert rigid_transform(T, "T", Refused, tol=1e-4) is T


def test_rigid_transform_wording_fields_and_numpy_errors():
    """issue 31 shared argument checks: a caller's own wording gets every field its
    failure has; with ``not_numbers=None`` numpy's own error goes through unchanged."""
    wording = TransformMessages(
        not_numbers=None,
        shape="{what}: shape {shape}",
        non_finite="{what}: entries {entries}",
        bottom_row="{what}: row {row}",
        rotation="{what}: ortho {ortho:.1f} det {det:.1f}",
    )
    with pytest.raises(ValueError, match="could not convert") as info:
        rigid_transform("abc", "P", Refused, messages=wording)
    assert not isinstance(info.value, Refused)
    with pytest.raises(Refused, match=r"^P: shape \(4,\)$"):
        rigid_transform(np.zeros(4), "P", Refused, messages=wording)
    bad = np.eye(4)
    bad[0, 1] = math.inf
    with pytest.raises(Refused, match=r"^P: entries \[\[1\.0, inf, 0\.0, 0\.0\], "):
        rigid_transform(bad, "P", Refused, messages=wording)
    with pytest.raises(Refused, match=r"^P: row \[0\.0, 0\.0, 0\.0, 2\.0\]$"):
        rigid_transform(np.diag([1.0, 1.0, 1.0, 2.0]), "P", Refused, messages=wording)
    with pytest.raises(Refused, match=r"^P: ortho 3\.0 det 8\.0$"):
        rigid_transform(np.diag([2.0, 2.0, 2.0, 1.0]), "P", Refused, messages=wording)


# -- numbers -----------------------------------------------------------------------------


def test_finite_number_accepts_what_float_takes():
    """issue 31 shared argument checks: ints, floats, numpy scalars and numeric strings
    come back as floats; bools only with ``allow_bool``."""
    assert finite_number(3, "x", Refused) == 3.0 and isinstance(finite_number(3, "x", Refused),
                                                                float)
    assert finite_number(np.float32(0.5), "x", Refused) == 0.5
    assert finite_number("1.5", "x", Refused) == 1.5
    assert finite_number(-2.0, "x", Refused) == -2.0
    with pytest.raises(Refused, match=r"^x must be a number, got True$"):
        finite_number(True, "x", Refused)
    assert finite_number(True, "x", Refused, allow_bool=True) == 1.0


@pytest.mark.parametrize("bad, message", [
    (None, r"^x must be a number, got None$"),
    ("fast", r"^x must be a number, got 'fast'$"),
    ([1.0], r"^x must be a number, got \[1\.0\]$"),
    (math.nan, r"^x must be finite, got nan$"),
    (-math.inf, r"^x must be finite, got -inf$"),
    ("inf", r"^x must be finite, got 'inf'$"),
])
def test_finite_number_refusals(bad, message):
    """issue 31 shared argument checks: what is no number, or no finite one, raises the
    error class given, in the default wording (naming the value as given)."""
    with pytest.raises(Refused, match=message):
        finite_number(bad, "x", Refused)


def test_numbers_only_refuses_strings_and_numpy_ints():
    """issue 31 shared argument checks: ``numbers_only`` takes int and float instances only
    (numpy's float64 is a float), not everything ``float()`` converts."""
    assert finite_number(np.float64(2.0), "x", Refused, numbers_only=True) == 2.0
    assert positive_number(7, "x", Refused, numbers_only=True) == 7.0
    for bad in ("1.5", np.int64(3), np.float32(1.0), True):
        with pytest.raises(Refused, match="must be a number"):
            finite_number(bad, "x", Refused, numbers_only=True)


def test_positive_number():
    """issue 31 shared argument checks: zero and below are refused after the number checks;
    ``NumberMessages.uniform`` words every failure alike."""
    assert positive_number(1e-12, "dt (s)", Refused) == 1e-12
    for bad in (0, 0.0, -1.0):
        with pytest.raises(Refused, match=r"^dt \(s\) must be positive, got "):
            positive_number(bad, "dt (s)", Refused)
    with pytest.raises(Refused, match="must be finite"):
        positive_number(math.inf, "dt (s)", Refused)
    one = NumberMessages.uniform("{what} must be a finite number of seconds > 0, got {value!r}")
    for bad in (True, "x", math.nan, -0.5):
        with pytest.raises(Refused, match=r"^dt must be a finite number of seconds > 0, got "):
            positive_number(bad, "dt", Refused, messages=one)


def test_finite_array():
    """issue 31 shared argument checks: a finite array comes back as a float array (the same
    one when it already is); NaN or infinities raise, naming the shape; numpy's conversion
    error goes through unless a wording for it is given."""
    a = np.array([[1.0, 2.0], [3.0, 4.0]])
    assert finite_array(a, "a", Refused) is a
    assert finite_array([1, 2], "a", Refused).dtype == float
    assert finite_array(5, "a", Refused).shape == ()
    with pytest.raises(Refused, match=r"^a has non-finite entries$"):
        finite_array([1.0, math.nan], "a", Refused)
    with pytest.raises(Refused, match=r"^a: 2 x 1 with NaN$"):
        finite_array([[math.inf], [0.0]], "a", Refused,
                     non_finite="{what}: {shape[0]} x {shape[1]} with NaN")
    with pytest.raises(ValueError) as info:
        finite_array([[1.0], [2.0, 3.0]], "a", Refused)
    assert not isinstance(info.value, Refused)
    with pytest.raises(Refused, match=r"^a is no array: 'x'$"):
        finite_array("x", "a", Refused, not_numbers="{what} is no array: {value!r}")


# -- the layers keep their own errors and wording -------------------------------------------


def test_each_layer_keeps_its_error_class_and_wording():
    """issue 31 shared argument checks: the same malformed pose through control's
    ``as_transform``, the arm's ``check_pose`` and safety's ``as_pose`` raises each layer's
    own error in each layer's own words."""
    from oralnav.control.errors import GeometryError
    from oralnav.control.geometry import as_transform
    from oralnav.drivers.arm.base import ArmCommandError, check_pose
    from oralnav.safety.errors import InputError
    from oralnav.safety.limits import as_pose

    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(GeometryError, match=r"^T: not a proper rotation \(\|R\^T R - I\| = "
                                            r"0\.00e\+00, det = -1\.000000\)$"):
        as_transform(reflection, what="T")
    with pytest.raises(ArmCommandError, match=r"^T rotation block is not a proper rotation "
                                              r"\(orthonormal, det \+1\)$"):
        check_pose(reflection, "T")
    with pytest.raises(InputError, match=r"^T rotation block is not a rotation "):
        as_pose(reflection, "T")

    short = np.eye(3)
    with pytest.raises(GeometryError, match=r"^T: expected a 4x4 transform, got shape \(3, 3\)$"):
        as_transform(short, what="T")
    with pytest.raises(ArmCommandError, match=r"^T must have shape \(4, 4\), got \(3, 3\)$"):
        check_pose(short, "T")
    with pytest.raises(InputError, match=r"^T must be a 4x4 transform, got shape \(3, 3\)$"):
        as_pose(short, "T")

    with pytest.raises(ValueError) as info:  # numpy's own, as before the shared check
        as_transform("abc", what="T")
    assert not isinstance(info.value, GeometryError)
    with pytest.raises(ArmCommandError, match=r"^T must be a 4x4 array of numbers, got 'abc'$"):
        check_pose("abc", "T")

    nearly = np.eye(4)
    nearly[3, 0] = 1e-7
    assert check_pose(nearly, "T")[3, 0] == 0.0  # the arm gets an exact bottom row
    assert as_pose(nearly, "T") is nearly and as_transform(nearly) is nearly


def test_the_module_imports_no_other_layer():
    """issue 31 shared argument checks: oralnav.checks is a leaf (numpy and the standard
    library), so every layer may import it."""
    code = ("import sys, oralnav.checks\n"
            "print(sorted(m for m in sys.modules if m.startswith('oralnav')))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "['oralnav', 'oralnav.checks']"
