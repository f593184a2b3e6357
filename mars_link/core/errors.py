"""Errors that carry a message meant for the user (one line, no traceback)."""

import argparse
import difflib
from collections.abc import Iterable
from typing import NoReturn


class UserInputError(ValueError):
    """Bad input from the user (scenario, CLI, map...): reported as one line, exit code 2."""


class OneLineArgumentParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one UserInputError line (exit 2), no usage dump."""

    def error(self, message: str) -> NoReturn:
        raise UserInputError(f"{self.prog}: {message}")


class EnvironmentFailure(RuntimeError):
    """The machine refused (read-only or full disk, permission, port in use): the run could not start,
    one line, exit code 3."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C's KeyboardInterrupt (so every cleanup that Ctrl-C
    runs runs for it too), told apart by the exit code: 143 (128 + SIGTERM) instead of 130."""


class PortUnavailable(EnvironmentFailure, UserInputError):
    """A port that cannot be bound (in use, not permitted): the machine's refusal, exit 3; still a
    UserInputError for the processes that catch only those (one line either way)."""


def did_you_mean(word: str, choices: Iterable[str]) -> str:
    """"; did you mean 'x'?" for the closest known names to a misspelled one (difflib), else "": appended
    to the one error line, so a typo costs one look instead of a listing."""
    close = difflib.get_close_matches(word, [str(c) for c in choices], n=3, cutoff=0.6)
    if not close:
        return ""
    return "; did you mean " + " or ".join(repr(c) for c in close) + "?"
