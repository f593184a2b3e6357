"""Errors that carry a message meant for the user (one line, no traceback)."""


class UserInputError(ValueError):
    """Bad input from the user (scenario, CLI, map...): reported as one line, exit code 2."""


class EnvironmentFailure(RuntimeError):
    """The machine refused (read-only or full disk, permission, port in use): one line, exit code 1."""
