"""Docking latches in the world: a latch that opens splits a body, facing engaged latches at their dock
pose merge two bodies, and each unit's latch sensor reports its latched sides (JSBSim bodies, the
world's own step)."""

from __future__ import annotations

import numpy as np

from mars_link.core.assembly import AssemblyModel
from mars_link.core.latches import ALL_SIDES, components, neighbour_links, side_toward
from mars_link.core.messages import ActuatorOutput
from sitl.docking import momentum
from sitl.physics import JsbsimBody
from sitl.world import World, WorldConfig

RIGHT, LEFT = 1 << 1, 1 << 3


def _masks(world: World) -> dict[int, int]:
    return {p.unit_id: p.latches for p in world.sense()}


def _hover(world: World, unit: int, latch_setpoint: int = ALL_SIDES, share: float = 0.0) -> None:
    world.actuate(ActuatorOutput(world.t_s, unit, np.full(4, share), latch_setpoint))


def test_side_geometry_and_components():
    assert side_toward((0, 0), (0, 1)) == 1 and side_toward((1, 0), (0, 0)) == 0 and side_toward((0, 0), (1, 1)) is None
    links = neighbour_links({1: (0, 0), 2: (0, 1), 3: (1, 1)})
    assert links == {frozenset((1, 2)): (1, 3), frozenset((2, 3)): (2, 0)}
    assert components([1, 2, 3], [frozenset((2, 3))]) == [{1}, {2, 3}]


def test_an_opened_latch_splits_the_body_with_momentum_kept_and_the_sensors_say_so():
    model = AssemblyModel.from_layout(["XX"], "mars-ftcc")
    world = World(model, WorldConfig(noise=False), np.zeros(3))
    assert _masks(world) == {1: RIGHT, 2: LEFT}
    for u in (1, 2):
        _hover(world, u)
    world.advance()
    assert len(world.bodies) == 1
    s0 = world.body_state(1)
    p0, _ = momentum([s0], [world.body_of(1).model])
    _hover(world, 1, ALL_SIDES & ~RIGHT)  # unit 1 opens its right latch: the only link goes
    _hover(world, 2)
    world.advance()
    assert len(world.bodies) == 2 and world.body_of(1) is not world.body_of(2)
    assert _masks(world) == {1: 0, 2: 0}
    assert [e["type"] for e in world.latch_events] == ["released"]
    states = [world.body_state(u) for u in (1, 2)]
    p1, _ = momentum(states, [world.body_of(u).model for u in (1, 2)])
    assert np.allclose(p1, p0, atol=1e-6)
    world.close()


def _two_free_units(gap_m: float, engaged_2: int = ALL_SIDES) -> World:
    model = AssemblyModel.from_layout(["XX"], "mars-ftcc")
    single = AssemblyModel.from_layout(["X"], model.vehicle)
    bodies = [(single, (u,), JsbsimBody(single, physics_hz=500.0, position_ned_m=(0.0, e, 0.0)))
              for u, e in ((1, 0.0), (2, gap_m))]
    world = World(model, WorldConfig(noise=False), bodies=bodies)
    for u in (1, 2):
        _hover(world, u, ALL_SIDES if u == 1 else engaged_2)
    return world


def test_facing_engaged_latches_at_the_dock_pose_close_and_merge_the_bodies():
    pitch = AssemblyModel.from_layout(["X"], "mars-ftcc").vehicle.pitch_m
    world = _two_free_units(pitch + 0.01)  # 1 cm off the dock pose, at rest: within the 2 cm tolerance
    world.advance()
    assert len(world.bodies) == 1 and world.body_of(1).units == (1, 2)
    assert _masks(world) == {1: RIGHT, 2: LEFT}
    (ev,) = world.latch_events
    assert ev["type"] == "dock_latched" and 0.005 < ev["position_error_m"] < 0.015
    world.close()


def test_no_dock_when_a_facing_latch_is_open_or_the_pose_is_off():
    pitch = AssemblyModel.from_layout(["X"], "mars-ftcc").vehicle.pitch_m
    for world in (_two_free_units(pitch + 0.01, ALL_SIDES & ~LEFT), _two_free_units(pitch + 0.05)):
        world.advance()
        assert len(world.bodies) == 2 and _masks(world) == {1: 0, 2: 0} and not world.latch_events
        world.close()
