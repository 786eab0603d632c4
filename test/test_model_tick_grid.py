"""The fixed stamp grid (model.tick_grid) of the realtime plant and the excitation timer."""

from __future__ import annotations

import pytest

from piezo_stage.model.tick_grid import TickGrid

pytestmark = pytest.mark.unit


def test_on_time_ticks_get_one_instant_each():
    grid = TickGrid(period_ns=1000, max_backlog=10)
    assert list(grid.due(5000)) == [5000]
    assert list(grid.due(5999)) == []  # early: the next instant is 6000
    assert list(grid.due(6000)) == [6000]
    assert list(grid.due(7400)) == [7000]  # late by less than a period: one instant, its own stamp


def test_a_late_tick_gets_every_missed_instant_in_order():
    grid = TickGrid(period_ns=1000, max_backlog=10)
    grid.due(0)
    assert list(grid.due(4500)) == [1000, 2000, 3000, 4000]
    assert list(grid.due(5000)) == [5000]
    assert grid.dropped == 0


def test_a_long_stall_drops_the_oldest_and_resumes_on_the_grid():
    grid = TickGrid(period_ns=1000, max_backlog=3)
    grid.due(0)
    assert list(grid.due(10_200)) == [10_000]  # 10 instants due, more than 3: only the latest
    assert grid.dropped == 9
    assert list(grid.due(11_000)) == [11_000]  # still on the same grid


def test_bad_arguments_are_refused():
    with pytest.raises(ValueError):
        TickGrid(period_ns=0, max_backlog=1)
    with pytest.raises(ValueError):
        TickGrid(period_ns=1000, max_backlog=0)
