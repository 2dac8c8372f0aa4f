"""The `sim` instrument plug-in (entry point in pyproject.toml): the simulated cell, for `hil sim`, `hil demo`
and the scripted operator's hands.

Loading the plug-in is light: the cell, its servers and its options are imported only when a method runs.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from fakes.control_client import ControlClient
from fakes.launch import RunningCell
from hil.instruments.plugins import ControlChannel


class SimulatedCellPlugin:
    """The simulated cell: a fake UR controller and a fake emScon tracker on one loopback address."""

    kind = "simulator"
    summary = "the simulated cell: fake UR controller and fake emScon tracker on a loopback address"

    @property
    def description(self) -> str:
        """What the cell process does, for `hil sim --help`."""
        from fakes.sim import DESCRIPTION

        return DESCRIPTION

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        """Every option of `python -m fakes.sim`."""
        from fakes.sim import add_sim_arguments

        add_sim_arguments(parser)

    def add_effects_argument(self, parser: argparse.ArgumentParser) -> None:
        """`--effects`, the cell's physical effects."""
        from fakes.sim import add_effects_argument

        add_effects_argument(parser)

    def check_effects(self, args: argparse.Namespace) -> dict[str, bool]:
        """The effect flags chosen by `--effects`; a SimOptionError (a PluginOptionError) lists the known ones."""
        from fakes.sim import effects_from_args

        return {name: bool(on) for name, on in effects_from_args(args).items()}

    def check_arguments(self, args: argparse.Namespace) -> None:
        """Refuse bad options of `add_arguments` (SimOptionError) before anything starts."""
        from fakes.sim import sim_options

        sim_options(args)

    def serve(self, args: argparse.Namespace, on_ready: Callable[[dict, dict], None] | None = None) -> int:
        """Run the cell in this process until SIGINT/SIGTERM."""
        from fakes.sim import sim_options
        from fakes.sim_process import run_cell

        options = sim_options(args)
        options.on_ready = on_ready
        return run_cell(options)

    @contextmanager
    def launch(
        self,
        robot: str,
        seed: int,
        time_scale: float,
        effects: str,
        host: str | None = None,
        control_port: int = 0,
    ) -> Iterator[RunningCell]:
        """Start `python -m fakes.sim` on a free loopback address (or `host`, control on `control_port`);
        stopped when the context ends."""
        from fakes.launch import sim_cell

        extra = ("--effects", effects, "--control-port", str(control_port))
        with sim_cell(robot=robot, seed=seed, time_scale=time_scale, host=host, extra_args=extra) as cell:
            yield cell

    def connect_control(self, address: str) -> ControlClient:
        """A client of the cell's control channel."""
        return ControlClient(address)

    def clock(self, control: ControlChannel) -> Callable[[], float]:
        """The cell's physics clock as UNIX seconds (the cell's start plus its simulated seconds of activity)."""
        return lambda: float(control.call("cell.clock")["unix_s"])


plugin = SimulatedCellPlugin()
