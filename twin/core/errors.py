"""The project's error base: a problem a user can fix, with a message that says what and how."""


class AimbenchError(Exception):
    """Base of every documented aimbench error.

    The message names the problem and what to do about it; the CLI prints it as one line.
    Modules derive their own errors from it (for example a malformed packet or a Grbl alarm).
    """
