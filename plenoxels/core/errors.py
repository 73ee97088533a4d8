"""The one exception type for mistakes a user can fix.

The CLI prints its message as a single line and exits with code 2; anything else is a bug and keeps
its traceback.
"""


class UserError(Exception):
    """Bad input or settings: the message says what is wrong and what to do."""


def require(condition: bool, message: str) -> None:
    """For `check()` methods: one line that names the key and the allowed values."""
    if not condition:
        raise UserError(message)
