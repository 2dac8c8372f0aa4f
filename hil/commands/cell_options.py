"""The `--effects` option of the commands that build a simulated cell (`hil sim`, `hil demo`), as CLI errors.

The option itself belongs to the simulated cell plug-in; here its bad values become a CliError.
"""

from __future__ import annotations

import argparse

from hil.commands.errors import CliError
from hil.instruments.plugins import CellSimulator, PluginError, PluginOptionError, cell_simulator

__all__ = ["add_effects_argument", "effect_flags", "simulator"]


def simulator() -> CellSimulator:
    """The simulated cell plug-in; a missing one ends the command with what to install."""
    try:
        return cell_simulator()
    except PluginError as exc:
        raise CliError(exc.message, exc.remedy) from exc


def add_effects_argument(parser: argparse.ArgumentParser) -> None:
    """Add the simulated cell's `--effects` option."""
    simulator().add_effects_argument(parser)


def effect_flags(args: argparse.Namespace) -> dict[str, bool]:
    """The cell's effect flags from `--effects`; an unknown name ends the command with the list of known ones."""
    try:
        return simulator().check_effects(args)
    except PluginOptionError as exc:
        raise CliError(exc.message, exc.remedy) from exc
