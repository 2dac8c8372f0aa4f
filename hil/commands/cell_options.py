"""The `--effects` option of the commands that build a simulated cell (`hil sim`, `hil demo`), as CLI errors.

The option itself belongs to the simulated cell (`fakes.sim`); here its bad values become a CliError.
"""

from __future__ import annotations

import argparse

from fakes.cell import EffectFlags
from fakes.sim import SimOptionError, add_effects_argument, effects_from_args
from hil.commands.errors import CliError

__all__ = ["add_effects_argument", "effect_flags"]


def effect_flags(args: argparse.Namespace) -> EffectFlags:
    """SimCellConfig flags from `--effects`; an unknown name ends the command with the list of known ones."""
    try:
        return effects_from_args(args)
    except SimOptionError as exc:
        raise CliError(exc.message, exc.remedy) from exc
