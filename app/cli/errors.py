"""The command line's error for users: a message, not a traceback (``error: ...``, exit code 2)."""


class UserError(Exception):
    """A problem with the user's input that deserves a message, not a traceback."""
