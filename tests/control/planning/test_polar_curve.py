"""Closed polar curves of piecewise cubics (seed 004, eqs. 1-6)."""

import math

import numpy as np
import pytest

from oralnav.control.errors import PlanningError
from oralnav.control.planning import polar_curve as pc


@pytest.mark.parametrize("n", [3, 6, 15, 20])
def test_local_form_equals_the_papers_linear_system(n):
    """Eqs. 3-5: the curve from the paper's absolute-theta coefficients (solved from M a = b)
    equals the local Hermite form used by every query, at every angle."""
    rng = np.random.default_rng(n)
    p = rng.uniform(0.02, 0.04, n)
    th = np.linspace(0, 2 * math.pi, 997, endpoint=False)
    C = pc.segment_coefficients(p)
    k = np.minimum((th / (2 * math.pi / n)).astype(int), n - 1)
    paper = C[k, 0] + C[k, 1] * th + C[k, 2] * th ** 2 + C[k, 3] * th ** 3
    assert np.allclose(pc.basis(th, n) @ p, paper, atol=1e-10)
    assert np.allclose(pc.evaluate(p, th), paper, atol=1e-10)


@pytest.mark.parametrize("n", [4, 9, 15])
def test_constraints_of_eq2_hold_at_the_knots(n):
    """Eq. 2: at each knot the curve equals its control point and its slope is the
    central difference N (rho_{i+2} - rho_i) / (4 pi), cyclically."""
    rng = np.random.default_rng(3)
    p = rng.uniform(10, 30, n)
    h = 2 * math.pi / n
    knots = np.arange(n) * h
    assert np.allclose(pc.evaluate(p, knots), p)
    eps = 1e-6
    slope = (pc.evaluate(p, knots + eps) - pc.evaluate(p, knots - eps)) / (2 * eps)
    expect = n * (np.roll(p, -1) - np.roll(p, 1)) / (4 * math.pi)
    assert np.allclose(slope, expect, rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("n", [3, 8, 15, 20])
def test_area_closed_form_matches_eq6_and_quadrature(n):
    """Eq. 6: the quadratic-form area equals the paper's closed form and a dense
    quadrature of rho^2 / 2."""
    rng = np.random.default_rng(10 + n)
    p = rng.uniform(20, 40, n)
    th = np.linspace(0, 2 * math.pi, 40001)
    quad = 0.5 * np.trapezoid(pc.evaluate(p, th) ** 2, th)
    assert pc.area(p) == pytest.approx(quad, rel=1e-7)
    assert pc.area_eq6(pc.segment_coefficients(p)) == pytest.approx(quad, rel=1e-6)


def test_circle_and_shrink():
    """A constant curve is a circle (area pi r^2) and shrinking by r (eq. 12) is p - r,
    since the basis weights sum to one."""
    p = np.full(15, 0.03)
    assert pc.area(p) == pytest.approx(math.pi * 0.03 ** 2, rel=1e-12)
    th = np.random.default_rng(0).uniform(0, 7, 100)
    assert np.allclose(pc.basis(th, 15).sum(axis=1), 1.0)
    q = np.random.default_rng(1).uniform(0.02, 0.03, 15)
    assert np.allclose(pc.evaluate(q - 0.006, th), pc.evaluate(q, th) - 0.006)


def test_area_gradient_is_G_p():
    """dS/dp = G p (used by the fits' analytic gradient)."""
    rng = np.random.default_rng(5)
    p = rng.uniform(1, 2, 12)
    G = pc.area_matrix(12)
    eps = 1e-6
    num = [(pc.area(p + eps * e) - pc.area(p - eps * e)) / (2 * eps) for e in np.eye(12)]
    assert np.allclose(num, G @ p, rtol=1e-6)


def test_too_few_points_refused():
    """A closed cubic curve needs at least 3 control points."""
    with pytest.raises(PlanningError, match="at least 3"):
        pc.basis(np.zeros(3), 2)
