"""The ``perception`` service on a real Zenoh session over loopback."""

from __future__ import annotations

import asyncio
import dataclasses
import time

import numpy as np
import pytest

from onboard.contracts import messages as m
from onboard.contracts.binary_messages import CELL_OCCUPIED, decode_grid, encode_depth
from onboard.contracts.params import PerceptionParams
from onboard.contracts.topics import TOPICS
from services.runtime.peers import query_status
from services.perception import PerceptionService
from services.runtime.zenoh_session import open_session
from test_perception_pipeline import TREES, render
from helpers import wait_for

NS = "archer/perception-test"



def _state(x: float, y: float) -> m.StateEstimate:
    return m.StateEstimate(
        position=[x, y, 0.5], velocity=[0.0, 0.0, 0.0], quat=[1.0, 0.0, 0.0, 0.0], omega=[0.0, 0.0, 0.0],
        wheel_vel=[0.0, 0.0, 0.0], foot_pos=0.0, foot_vel=0.0, contact=False, phase="flight",
        pos_vel_cov=[0.0] * 36, att_cov=[0.0, 0.0, 0.0],
    )


@pytest.mark.parametrize("mode", ["obstacles", "free"])
def test_service_publishes_polytopes_and_grid_at_rate(zenoh_router, mode):
    params = dataclasses.replace(PerceptionParams(), mode=mode, rate_hz=10.0)

    async def scenario() -> None:
        service = PerceptionService(ns=NS, endpoint=zenoh_router, params={"perception": params})
        task = asyncio.create_task(service.run())
        client = open_session(zenoh_router, "peer")
        sets: list[tuple[float, m.PolytopeSet]] = []
        grids = []
        subs = [
            client.declare_subscriber(TOPICS["polytopes"].key(NS),
                                      lambda s: sets.append((time.monotonic(), m.decode(s.payload.to_bytes(), m.PolytopeSet)))),
            client.declare_subscriber(TOPICS["grid"].key(NS), lambda s: grids.append(decode_grid(s.payload.to_bytes()))),
        ]
        try:
            await wait_for(lambda: service.state == "running")
            await asyncio.sleep(0.3)  # let the subscriptions meet
            client.put(TOPICS["state"].key(NS), m.encode(_state(0.0, 0.0)))
            await asyncio.sleep(0.2)
            assert sets == []  # nothing is published before a view is fused
            depth_key = TOPICS["depth"].key(NS)
            client.put(depth_key, b"ARCB garbage")  # malformed: rejected and counted
            for k, yaw in enumerate((0.0, 0.7, -0.7)):
                img = render((0.0, 0.0, 0.5), yaw=yaw, cylinders=TREES, stamp_ns=(k + 1) * 200_000_000)
                client.put(depth_key, encode_depth(img))
            client.put(depth_key, encode_depth(render((0.0, 0.0, 0.5), stamp_ns=100)))  # older: out of order
            await wait_for(lambda: service.counters.get("views") == 3 and len(sets) >= 12)
            last = sets[-1][1]
            assert last.mode == mode and last.source == "perception" and last.polytopes
            # Rate: the stamps of successive sets, within the 4-20 Hz band.
            stamps = np.array([s.stamp_ns for _, s in sets[-10:]]) / 1e9
            rate = 1.0 / np.median(np.diff(stamps))
            assert 4.0 <= rate <= 20.0, rate
            grid = grids[-1]
            assert grid.cells.shape == (params.grid_cells, params.grid_cells)
            assert (grid.cells == CELL_OCCUPIED).sum() > 10
            if mode == "obstacles":
                for tx, ty, r, _ in TREES:
                    front = np.array([tx - 0.999 * r, ty])
                    assert any(np.all(np.array(p.A) @ front <= np.array(p.b) + 1e-6) for p in last.polytopes)
            else:
                robot = np.array([0.0, 0.0])
                assert any(np.all(np.array(p.A) @ robot <= np.array(p.b)) for p in last.polytopes)
            status = await asyncio.to_thread(query_status, client, NS, "perception")
            assert status.counters["rejected.depth"] >= 1
            assert status.counters["rejected.depth_out_of_order"] == 1
            assert status.extra["views"] == 3.0 and status.extra["polygons"] == len(last.polytopes)
            assert status.rates_hz["polytopes"] > 0
        finally:
            for sub in subs:
                sub.undeclare()
            service.stopping.set()
            await asyncio.wait_for(task, 10.0)
            client.close()

    asyncio.run(asyncio.wait_for(scenario(), 90))


def test_service_refuses_a_rate_outside_the_band(zenoh_router):
    params = dataclasses.replace(PerceptionParams(), rate_hz=50.0)

    async def scenario() -> None:
        service = PerceptionService(ns=NS, endpoint=zenoh_router, params={"perception": params})
        with pytest.raises(ValueError, match="rate_hz"):
            await asyncio.wait_for(service.run(), 30)

    asyncio.run(scenario())


# real time: loops at their rate, processes and Zenoh over loopback share two loaded cores
pytestmark = pytest.mark.timing_sensitive(reason="real-time loops, processes or Zenoh over loopback on a shared host")
