"""Help text that shows a default only where there is one: a required option or an empty default says none."""

from __future__ import annotations

import argparse


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """argparse's defaults formatter without '(default: None)' on required options and optional outputs."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.required or action.default is None or action.default is argparse.SUPPRESS:
            return action.help
        if isinstance(action.default, bool) and action.nargs == 0:  # a flag: its default is "off"
            return action.help
        return super()._get_help_string(action)
