"""Errors that carry a message meant for the user (one line, no traceback)."""

import argparse


class UserInputError(ValueError):
    """Bad input from the user (scenario, CLI, map...): reported as one line, exit code 2."""


class OneLineArgumentParser(argparse.ArgumentParser):
    """argparse that reports a usage error as one UserInputError line (exit 2), no usage dump."""

    def error(self, message: str) -> None:
        raise UserInputError(f"{self.prog}: {message}")


class EnvironmentFailure(RuntimeError):
    """The machine refused (read-only or full disk, permission, port in use): one line, exit code 1."""


class PortUnavailable(EnvironmentFailure, UserInputError):
    """A port that cannot be bound (in use, not permitted): the machine's refusal, exit 1; still a
    UserInputError for the processes that catch only those (one line either way)."""
