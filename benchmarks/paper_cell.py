"""A simulated cell for the paper benchmarks: procedures through ur-rtde and emScon into campaign files.

The cell carries hidden geometric errors and physics no geometric model holds (gravity compliance, the
gears' cyclic errors, and the thermal growth of a warming arm), so that neither paper's own model family is
the whole truth. Rows of a paper table are dicts with the columns of COLUMNS.
"""

from __future__ import annotations

import sys
import tempfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run on its own: python benchmarks/paper_grid.py
    sys.path.insert(0, str(ROOT))

from hil.runner.cell_config import CellConfig  # noqa: E402
from hil.runner.session import Session  # noqa: E402

COLUMNS = ("paper", "quantity", "paper_value", "ours", "unit", "note")
EFFECTS = (
    "gravity_compliance,cyclic,thermal_expansion"  # what the simulated cell adds to its geometric errors
)
TIME_SCALE = 200.0


@contextmanager
def paper_cell(robot: str, seed: int, cell_toml_extra: str = "") -> Iterator[tuple[CellConfig, Path]]:
    """Start `hil sim` for `robot`, write its cell.toml (plus `cell_toml_extra`, e.g. a [grid] section) in a
    temporary folder; yield the configuration and the folder. The cell stops on leaving."""
    from fakes.launch import sim_cell
    from hil.commands.sim_cell import write_sim_cell
    from hil.runner.cell_config import load_cell_config

    with (
        tempfile.TemporaryDirectory(prefix="hil-paper-") as tmp,
        sim_cell(robot=robot, seed=seed, time_scale=TIME_SCALE, extra_args=("--effects", EFFECTS)) as cell,
    ):
        folder = Path(tmp)
        path = folder / "cell.toml"
        write_sim_cell(path, cell.info, cell.control.call("ground_truth"), TIME_SCALE)
        if cell_toml_extra:
            path.write_text(path.read_text() + "\n" + cell_toml_extra)
        yield load_cell_config(path), folder


def run_campaign(config: CellConfig, campaign: Path, body: Callable[[Session], None]) -> None:
    """Open a Session on the cell (the scripted operator moves the simulated SMRs), register, run `body`."""
    from contextlib import ExitStack

    from hil.commands.native_output import capture_native_output
    from hil.runner.registry import load
    from hil.station.instruments import open_session, simulated_operator

    with ExitStack() as stack:
        stack.enter_context(capture_native_output(verbose=False))
        session = open_session(config, campaign, simulated_operator(config.simulator_control), stack)
        with session:
            load("registration")(session)
            body(session)


def grid_datasets(campaign: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The grid_sampling procedure's grid and validation measurements as datasets."""
    from hil.data.store import campaign_dataset

    return campaign_dataset(campaign, "grid_sampling", "grid"), campaign_dataset(
        campaign, "grid_sampling", "validation"
    )


def norms_mm(error_m: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.asarray(error_m)[:, :3], axis=1) * 1e3


def row(paper: str, quantity: str, paper_value: float | None, ours: float, unit: str, note: str = "") -> dict:
    return dict(zip(COLUMNS, (paper, quantity, paper_value, float(ours), unit, note), strict=True))


def print_rows(rows: list[dict]) -> None:
    """The rows as a plain table: the paper's figure beside ours."""
    width = max(len(r["quantity"]) for r in rows) + 2
    print(f"{'quantity':<{width}}{'paper':>9}{'ours':>9}  unit  note")
    for r in rows:
        paper = "" if r["paper_value"] is None else f"{r['paper_value']:9.3f}"
        print(f"{r['quantity']:<{width}}{paper:>9}{r['ours']:9.3f}  {r['unit']:<4}  {r['note']}")
