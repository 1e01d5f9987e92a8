"""A simulated fault's `at_s` counts from the run's first tick, not from the simulated world's
clock, which already reads its registration and warm-up (30.9 s on the paper's cell) when the
run starts: a fault at 30 s used to fire at the first tick."""
from __future__ import annotations

from types import SimpleNamespace

from dt_runtime.service.cell import SimCell
from dt_runtime.service.runtime_config import Fault


class World:
    def __init__(self, t: float):
        self.t = t
        self.offsets: list[tuple[float, ...]] = []

    def inject_joint_offset(self, dq) -> None:
        self.offsets.append((self.t, *dq))

    def bump_camera(self, shift) -> None:  # pragma: no cover - not used here
        raise AssertionError("no camera fault in this test")


def _cell(world: World, *faults: Fault) -> SimCell:
    return SimCell(SimpleNamespace(), world, False, list(faults), SimpleNamespace(T_rdk=None, T_lt=None))


def test_a_fault_at_30_s_waits_30_simulated_seconds_after_the_first_tick():
    world = World(30.9)  # the world's clock when the run starts: registration and warm-up
    cell = _cell(world, Fault(at_s=30.0, joint_offset_rad=(0, 1e-3, 0, 0, 0, 0)))
    cell.inject_due_faults()
    assert world.offsets == [] and cell.t_start == 30.9
    world.t = 60.8
    cell.inject_due_faults()
    assert world.offsets == []  # 29.9 s into the run
    world.t = 61.0
    cell.inject_due_faults()
    cell.inject_due_faults()
    assert [o[0] for o in world.offsets] == [61.0]  # once, 30.1 s into the run


def test_a_fault_at_0_s_comes_with_the_first_tick():
    world = World(30.9)
    cell = _cell(world, Fault(at_s=0.0, joint_offset_rad=(0, 1e-3, 0, 0, 0, 0)))
    cell.inject_due_faults()
    assert len(world.offsets) == 1
