"""Errors that carry a message meant for the user (one line, no traceback)."""


class UserInputError(ValueError):
    """Bad input from the user (scenario, CLI, map...): reported as one line, exit code 2."""
