"""Issue 32, item 3: the hardware-in-the-loop cell's ground truth on loopback, and the
daemon's observer of it. ``TruthServer`` answers ``GET /truth?t=<s>`` with what
``truth_at(t)`` gives (400 for a bad ``t``, 404 when no capture answers);
``PeerTruth`` turns it into a reached target's TRE, and says nothing (None) rather than a
wrong figure when the peers do not answer or do not know the target. The whole main job on
the HIL cell is ``oralnav bench hil`` (minutes, and not yet reliable on a 2-core machine:
docs/navigation.md)."""

from __future__ import annotations

import json
import urllib.error
import urllib.request

import numpy as np
import pytest

from oralnav.daemon.sim_cell import PeerTruth
from oralnav.sim.errors import SimError
from oralnav.sim.hil.truth import TruthServer


def _truth_at(t):
    if t is not None and t < 10.0:
        raise SimError(f"no capture kept at or before {t:.6f} s")
    T_B_E = np.eye(4)
    T_B_E[:3, 3] = [0.1, 0.02, 0.3]
    return {"time": 12.5 if t is None else t, "T_B_tcp": np.eye(4), "T_B_E": T_B_E,
            "q": np.zeros(4), "targets_B": {"a": np.array([0.1, 0.02, 0.30003])}}


def test_truth_is_served_and_bad_requests_are_named() -> None:
    """GET /truth answers the newest capture's truth as JSON; ?t=20 that instant's; a t
    that is not a number is 400 naming it; a t before every capture is 404 with why; an
    unknown path is 404."""
    with TruthServer(_truth_at) as server:
        assert server.url.startswith("http://127.0.0.1:")
        with urllib.request.urlopen(server.url, timeout=5) as r:
            doc = json.load(r)
        assert doc["time"] == 12.5 and np.array(doc["T_B_E"]).shape == (4, 4)
        with urllib.request.urlopen(f"{server.url}?t=20", timeout=5) as r:
            assert json.load(r)["time"] == 20.0
        for query, code, words in [("?t=abc", 400, "t must be a finite number"),
                                   ("?t=nan", 400, "t must be a finite number"),
                                   ("?t=1", 404, "no capture kept")]:
            with pytest.raises(urllib.error.HTTPError) as err:
                urllib.request.urlopen(f"{server.url}{query}", timeout=5)
            assert err.value.code == code and words in json.load(err.value)["error"]
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(server.url.replace("/truth", "/other"), timeout=5)
        assert err.value.code == 404


def test_peer_truth_measures_the_tre_or_says_nothing() -> None:
    """PeerTruth: the distance (mm) between the true end-effector and the true target at
    the reaching frame's instant; None for a target the peers do not hold, an instant
    they have no capture for, or peers that do not answer."""
    with TruthServer(_truth_at) as server:
        observe = PeerTruth(server.url, timeout=2.0)
        assert observe("a", 20.0) == pytest.approx(0.03)
        assert observe("b", 20.0) is None
        assert observe("a", 1.0) is None
        url = server.url
    assert PeerTruth(url, timeout=0.5)("a", 20.0) is None  # the server is gone
