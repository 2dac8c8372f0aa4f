"""The `--effects` option shared by the commands that build a simulated cell (`hil sim`, `hil demo`)."""

from __future__ import annotations

import argparse

from fakes.cell import CELL_EFFECTS, parse_effect_flags


def add_effects_argument(parser: argparse.ArgumentParser) -> None:
    """Add `--effects` (comma-separated physical effects of the simulated cell, default gravity_compliance)."""
    parser.add_argument(
        "--effects",
        default="gravity_compliance",
        help=f"physical effects of the simulated cell, comma-separated from {', '.join(CELL_EFFECTS)} (the "
        "diagnosis' effect names), or 'none' (default: gravity_compliance, the PT paper's undeclared effect)",
    )


def effect_flags(args: argparse.Namespace) -> dict[str, bool]:
    """CellConfig flags from `--effects`; an unknown name ends the command with the list of known ones."""
    try:
        return parse_effect_flags(args.effects)
    except ValueError as exc:
        raise SystemExit(str(exc)) from exc
