"""A simulated cell with its cell.toml and a Session through the real drivers, for procedure tests."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from fakes.launch import RunningCell, sim_cell
from hil.commands.sim_cell import write_sim_cell
from hil.runner.cell_config import CellConfig, load_cell_config
from hil.runner.session import Session
from hil.station.instruments import open_session, simulated_operator


@contextmanager
def running_cell(
    folder: Path, time_scale: float = 50.0, **kwargs
) -> Iterator[tuple[RunningCell, CellConfig]]:
    """Start `hil sim`, write its cell.toml into `folder`, yield the cell and its configuration. 50 simulated
    seconds per wall second by default: the moves and the tracker's readings wait less, the results are the
    same (the cell advances by whole ticks of simulated time)."""
    with sim_cell(time_scale=time_scale, **kwargs) as cell:
        path = folder / "cell.toml"
        write_sim_cell(path, cell.info, cell.control.call("ground_truth"), time_scale)
        yield cell, load_cell_config(path)


@contextmanager
def session_on(config: CellConfig, campaign: Path) -> Iterator[Session]:
    """A Session on the cell (ur-rtde + emScon), the scripted operator moving the simulated SMR."""
    with ExitStack() as stack:
        session = open_session(config, campaign, simulated_operator(config.simulator_control), stack)
        with session:
            yield session
