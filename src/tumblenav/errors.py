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


class Interrupted(BaseException):
    """SIGINT or SIGTERM reached the command (raised by the CLI's signal handlers).

    A ``BaseException`` like ``KeyboardInterrupt``, so that no ``except Exception`` records it
    as a failed run. Whoever holds partial results says in ``kept`` what was kept and how to
    resume; the CLI prints it and exits with ``128 + signum`` (130 for SIGINT, 143 for SIGTERM).
    """

    def __init__(self, signum: int, kept: str | None = None) -> None:
        self.signum = signum
        self.kept = kept
        super().__init__(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum
