"""The needle's arc geometry and frame N (seed 002, Fig. 3)."""

import math

import numpy as np
import pytest

from oralnav.control.errors import NeedleError
from oralnav.control.needle.model import Needle


def test_frame_n_convention():
    """Frame N: base on +x, body toward +y, tip at the arc's end; a semicircular CT-1
    (13 mm radius) has a 40.8 mm wire."""
    n = Needle()
    assert np.allclose(n.base, [0.013, 0, 0])
    assert np.allclose(n.point(math.pi / 2), [0, 0.013, 0])
    assert np.allclose(n.tip, [-0.013, 0, 0], atol=1e-15)
    assert n.length == pytest.approx(0.013 * math.pi)
    pts = n.points(50)
    assert pts.shape == (50, 3) and np.allclose(np.linalg.norm(pts, axis=1), 0.013)
    t = n.tangent(np.linspace(0, math.pi, 7))
    assert np.allclose(np.linalg.norm(t, axis=1), 1.0)
    # the tangent points from the base toward the tip: along the arc's increasing phi
    eps = 1e-6
    fd = (n.point(1.0 + eps) - n.point(1.0 - eps)) / (2 * eps)
    assert np.allclose(fd / np.linalg.norm(fd), n.tangent(1.0))


@pytest.mark.parametrize("kw", [{"radius": 0.0}, {"radius": math.nan},
                                {"wire_diameter": 0.0}, {"wire_diameter": 0.02},
                                {"arc": 0.0}, {"arc": 7.0}])
def test_bad_needle_refused(kw):
    """Bad input: a needle the drive cannot model is refused with the value named."""
    with pytest.raises(NeedleError):
        Needle(**kw)


def test_too_few_arc_points_refused():
    """Bad input: an arc sampled at fewer than 2 points."""
    with pytest.raises(NeedleError, match="at least 2"):
        Needle().points(1)
