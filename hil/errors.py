"""The base of every error that tells the operator what happened and what to do next.

Robot and tracker errors, the command line's error and the campaign's stop all carry a one-line `message`
and a `remedy`; they differ only in their default remedy and in how the two read as one text.
"""

from __future__ import annotations


class ActionableError(Exception):
    """What happened (`message`) and what to do next (`remedy`); a subclass may give a default remedy."""

    remedy = "check the instrument and its connection, then run the command again"

    def __init__(self, message: str, remedy: str | None = None):
        if remedy is not None:
            self.remedy = remedy
        self.message = message
        super().__init__(self.text())

    def text(self) -> str:
        """The error as one line (its str): the message, then what to do next."""
        return f"{self.message} -- next: {self.remedy}"


class SessionSetupError(ActionableError):
    """A session could not be set up before anything moved: a driver plug-in missing, the campaign held by
    another run, the simulated cell's control channel not answering. Every front end shows it as it shows its
    own refusals (the command line as `hil <command>: ...`, the console on the page)."""

    remedy = "fix what is named above, then start again; nothing moved"
