"""Errors a user can cause: the CLI prints them as one line and exits 2."""


class UserError(Exception):
    """Bad input from a person (argument, file, configuration): one clear line, no traceback."""
