"""Exceptions that the CLI turns into a one-line message and exit status 2."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input (scenario, measurement file, option): reported in one line, exit status 2.

    ``where`` names the file and/or key path, ``what`` says what is wrong.
    """

    def __init__(self, what: str, where: str | None = None) -> None:
        self.what = what
        self.where = where
        super().__init__(f"{where}: {what}" if where else what)
