"""Issue 30: every pose the daemon publishes is rigid to 1e-9. What the daemon tests share
to check it: an observer's client of the REST API over a core, and the rigidity of every
``T`` in a ``GET /poses`` answer."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from oralnav.daemon.api import build_app
from oralnav.daemon.audit import AuditLog
from oralnav.daemon.auth import TokenStore

#: how far from rigid a published pose may be: ||R^T R - I|| (Frobenius), |det R - 1| and
#: the bottom row's deviation from [0, 0, 0, 1]
RIGID_TOL = 1e-9


def rigidity_error(T: Any) -> float:
    """How far the 4x4 ``T`` is from a rigid transform (the largest of the measures of
    :data:`RIGID_TOL`)."""
    T = np.asarray(T, dtype=float)
    R = T[:3, :3]
    return max(float(np.linalg.norm(R.T @ R - np.eye(3))), abs(float(np.linalg.det(R)) - 1.0),
               float(np.max(np.abs(T[3] - (0.0, 0.0, 0.0, 1.0)))))


@contextlib.asynccontextmanager
async def observer_client(core: Any, folder: Path) -> AsyncIterator[httpx.AsyncClient]:
    """An observer's client of the REST API over ``core`` (tokens and audit log in
    ``folder``), in process."""
    clear = TokenStore.generate(folder / "tokens.toml")
    audit = AuditLog(folder / "audit.jsonl").open()
    app = build_app(core, TokenStore.from_file(folder / "tokens.toml"), audit)
    try:
        async with httpx.AsyncClient(
                transport=httpx.ASGITransport(app=app), base_url="http://t",
                headers={"Authorization": f"Bearer {clear['observer']}"}) as client:
            yield client
    finally:
        audit.close()


async def poll_rigidity(client: httpx.AsyncClient, worst: dict[str, float]) -> dict:
    """``GET /poses`` once; ``worst`` (pose name -> largest :func:`rigidity_error` so far)
    takes in every pose of the answer, which is returned."""
    r = await client.get("/poses")
    assert r.status_code == 200, r.text
    poses = r.json()
    for name, p in poses.items():
        worst[name] = max(worst.get(name, 0.0), rigidity_error(p["T"]))
    return poses


def assert_rigid(worst: dict[str, float]) -> None:
    """Every pose polled by :func:`poll_rigidity` was rigid within :data:`RIGID_TOL`."""
    bad = {n: f"{e:.1e}" for n, e in worst.items() if not e < RIGID_TOL}
    assert not bad, f"GET /poses gave poses off rigid by more than {RIGID_TOL:g}: {bad}"
