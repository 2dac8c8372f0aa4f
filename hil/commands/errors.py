"""The one error a command raises for bad input or a failed step: what went wrong and what to do next.

`hil.cli.main` prints it as `hil <command>: <message>` and `  what to do: <remedy>` on stderr and exits 2.
"""

from __future__ import annotations

from hil.errors import ActionableError

EXIT_USAGE = 2


class CliError(ActionableError):
    """A command's failure for the operator: `message` (one line, what went wrong) and `remedy` (what to do)."""

    def __init__(self, message: str, remedy: str):
        super().__init__(message, remedy)

    def text(self) -> str:
        """The message alone: `render` prints the remedy on its own line."""
        return self.message

    @classmethod
    def from_text(
        cls, text: str, remedy: str = "fix the input named above and run the command again"
    ) -> CliError:
        """From a one-line "what is wrong; what to do" text (input checks, dataset errors): split at the last
        '; ' into message and remedy; a text without one gets the generic remedy."""
        message, sep, what_to_do = text.rpartition("; ")
        return cls(message, what_to_do) if sep and message else cls(text, remedy)

    def render(self, command: str) -> str:
        """The two stderr lines for `hil <command>`."""
        return f"{f'hil {command}'.strip()}: {self.message}\n  what to do: {self.remedy}"
