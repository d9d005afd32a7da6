"""Argument checks shared by every layer: finite and positive numbers, finite arrays, rigid
transforms.

A leaf module (numpy and the standard library only), so ``oralnav.control``,
``oralnav.drivers``, ``oralnav.safety`` and the rest may all import it. Each check takes
``what``, the name of the checked value as the message shows it, and ``error``, the exception
class it raises (called with the message alone), so each layer keeps raising its own type:
``GeometryError`` in control, a ``DriverError`` subclass in drivers, ``InputError`` in safety.

Messages are ``str.format`` templates with the fields each check lists. The default wording
is ``oralnav.safety``'s (and ``oralnav.control.guidance``'s for numbers), whose tests match on
it: change it only with them. Callers with wording of their own pass it through a
:class:`NumberMessages` or :class:`TransformMessages` kept beside the call.

Transforms follow docs/conventions.md: ``T_a_b`` is the 4x4 pose of frame b in frame a,
metres; the checks look at its structure only, never at its frames.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "ROTATION_TOL",
    "NumberMessages",
    "TransformMessages",
    "finite_array",
    "finite_number",
    "positive_number",
    "rigid_transform",
]

#: Default tolerance on a rotation block's ``|R^T R - I|`` (max abs entry) and on a bottom
#: row's distance from ``[0, 0, 0, 1]``: a pose built from float math or read from a file with
#: 6-7 digits is rigid to about 1e-6, not to machine precision.
ROTATION_TOL = 1e-6

_BOTTOM = np.array([0.0, 0.0, 0.0, 1.0])
_EYE3 = np.eye(3)


@dataclass(frozen=True)
class NumberMessages:
    """Wording of the number checks; each a template with the fields ``what`` and ``value``
    (the argument as given, use ``{value!r}``).

    Attributes:
        not_number: a bool (unless allowed), or a value ``float()`` refuses (or, with
            ``numbers_only``, anything but an ``int`` or ``float``).
        not_finite: NaN or an infinity.
        not_positive: zero or below (:func:`positive_number` only).
    """

    not_number: str = "{what} must be a number, got {value!r}"
    not_finite: str = "{what} must be finite, got {value!r}"
    not_positive: str = "{what} must be positive, got {value!r}"

    @classmethod
    def uniform(cls, template: str) -> NumberMessages:
        """One wording for every failure (e.g. ``"{what} must be a finite number > 0, got
        {value!r}"``)."""
        return cls(template, template, template)


@dataclass(frozen=True)
class TransformMessages:
    """Wording of :func:`rigid_transform`; templates with the field ``what`` and those named.

    Attributes:
        not_numbers: numpy cannot make a float array of it (field ``value``, the argument as
            given). ``None``: numpy's own ``TypeError``/``ValueError`` goes through unchanged.
        shape: not 4x4 (field ``shape``, a tuple).
        non_finite: NaN or infinite entries (field ``entries``, the 4x4 as nested lists).
        bottom_row: the bottom row is not ``[0, 0, 0, 1]`` (field ``row``, a list).
        rotation: the 3x3 block is no proper rotation (fields ``ortho``, ``|R^T R - I|`` as a
            float, and ``det``, its determinant).
    """

    not_numbers: str | None = "{what} must be a 4x4 transform, got {value!r}"
    shape: str = "{what} must be a 4x4 transform, got shape {shape}"
    non_finite: str = "{what} has non-finite entries"
    bottom_row: str = "{what} bottom row must be [0, 0, 0, 1], got {row}"
    rotation: str = ("{what} rotation block is not a rotation "
                     "(|R^T R - I| = {ortho:.2e}, det = {det:.3f})")


_NUMBER = NumberMessages()
_TRANSFORM = TransformMessages()


def finite_number(value: object, what: str, error: type[Exception], *,
                  allow_bool: bool = False, numbers_only: bool = False,
                  messages: NumberMessages = _NUMBER) -> float:
    """``value`` as a finite float, or ``error`` naming ``what``; the unit is the caller's.

    Args:
        allow_bool: accept ``True``/``False`` as 1.0/0.0 (refused by default: a flag passed
            for a number is a wiring mistake).
        numbers_only: accept ``int`` and ``float`` instances only (numpy's float64 is one),
            not everything ``float()`` converts, such as the string ``"1.5"``.
        messages: the wording (:class:`NumberMessages`; ``not_positive`` is unused here).
    """
    if (isinstance(value, bool) and not allow_bool) \
            or (numbers_only and not isinstance(value, int | float)):
        raise error(messages.not_number.format(what=what, value=value))
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise error(messages.not_number.format(what=what, value=value)) from None
    if not math.isfinite(out):
        raise error(messages.not_finite.format(what=what, value=value))
    return out


def positive_number(value: object, what: str, error: type[Exception], *,
                    allow_bool: bool = False, numbers_only: bool = False,
                    messages: NumberMessages = _NUMBER) -> float:
    """``value`` as a finite float > 0, or ``error`` naming ``what``; arguments as
    :func:`finite_number`'s."""
    out = finite_number(value, what, error, allow_bool=allow_bool, numbers_only=numbers_only,
                        messages=messages)
    if out <= 0.0:
        raise error(messages.not_positive.format(what=what, value=value))
    return out


def finite_array(value: object, what: str, error: type[Exception], *,
                 non_finite: str = "{what} has non-finite entries",
                 not_numbers: str | None = None) -> np.ndarray:
    """``value`` as a float array (``np.asarray``: no copy when it already is one) with
    finite entries only, or ``error`` naming ``what``. Any shape, any unit.

    Args:
        non_finite: template for NaN or infinite entries (fields ``what``, ``shape``).
        not_numbers: template for a value numpy cannot make a float array of (fields
            ``what``, ``value``); ``None``: numpy's ``TypeError``/``ValueError`` goes through.
    """
    try:
        out = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        if not_numbers is None:
            raise
        raise error(not_numbers.format(what=what, value=value)) from None
    if not np.all(np.isfinite(out)):
        raise error(non_finite.format(what=what, shape=out.shape))
    return out


def rigid_transform(value: object, what: str, error: type[Exception], *,
                    tol: float = ROTATION_TOL, det_tol: float | None = None,
                    copy: bool = False,
                    messages: TransformMessages = _TRANSFORM) -> np.ndarray:
    """``value`` as a float 4x4 rigid transform, or ``error`` naming ``what``.

    Checks, in this order: numbers, shape (4, 4), finite entries, a bottom row within ``tol``
    of ``[0, 0, 0, 1]``, and a proper rotation block: ``|R^T R - I| <= tol`` (max abs entry)
    and a determinant > 0, or within ``det_tol`` of 1 when ``det_tol`` is given. The bottom
    row is returned as given (within ``tol``), not rounded.

    Args:
        copy: return a private copy; otherwise ``np.asarray``'s result, which is ``value``
            itself when it already is a float array.
        messages: the wording (:class:`TransformMessages`).
    """
    # Plain max-abs arithmetic rather than np.allclose (~20 us): arms check every servo
    # set point with this, at the control rate.
    try:
        out = np.array(value, dtype=float) if copy else np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        if messages.not_numbers is None:
            raise
        raise error(messages.not_numbers.format(what=what, value=value)) from None
    if out.shape != (4, 4):
        raise error(messages.shape.format(what=what, shape=out.shape))
    if not np.isfinite(out).all():
        raise error(messages.non_finite.format(what=what, entries=out.tolist()))
    if np.abs(out[3] - _BOTTOM).max() > tol:
        raise error(messages.bottom_row.format(what=what, row=out[3].tolist()))
    R = out[:3, :3]
    ortho = float(np.abs(R.T @ R - _EYE3).max())
    det = float(np.linalg.det(R))
    # Orthonormal within tol leaves det near +1 or -1; det > 0 refuses a reflection, and
    # det_tol (for callers that want it) also bounds how far from 1 it may be.
    bad_det = det <= 0.0 if det_tol is None else abs(det - 1.0) > det_tol
    if ortho > tol or bad_det:
        raise error(messages.rotation.format(what=what, ortho=ortho, det=det))
    return out
