"""Cell configurations for tests: the one `hil sim --write-cell` would write for a seeded cell, as text."""

from __future__ import annotations

from fakes.cell import SimCellConfig, SimulatedCell
from hil.commands.sim_cell import sim_cell_values
from hil.runner.cell_config import format_cell_toml

ANNOUNCEMENT = {
    "robot": {"model": "ur10", "host": "127.0.0.9"},
    "tracker": {"url": "socket://127.0.0.9:7000"},
    "control": "127.0.0.9:4000",
}


def sim_cell_toml(seed: int = 0, time_scale: float = 10.0, robot: str = "ur10") -> str:
    """cell.toml text of a simulated cell of `robot` (a built-in robot file) with `seed` (no instruments
    are started)."""
    announcement = {**ANNOUNCEMENT, "robot": {**ANNOUNCEMENT["robot"], "model": robot}}
    return format_cell_toml(
        sim_cell_values(
            announcement,
            SimulatedCell().ground_truth() if (seed, robot) == (0, "ur10") else _truth(seed, robot),
            time_scale,
        )
    )


def _truth(seed: int, robot: str) -> dict:
    return SimulatedCell(SimCellConfig(robot=robot, seed=seed)).ground_truth()
