"""The project's error base: a problem a user can fix, with a message that says what and how."""


class AimbenchError(Exception):
    """Base of every documented aimbench error.

    The message names the problem and what to do about it; the CLI prints it as one line.
    Modules derive their own errors from it (for example a malformed packet or a Grbl alarm).
    """


#: Most problems one error line lists (a file of 1,000 unknown keys made a 143,000-character
#: line that hid the first, which is the one to fix).
MAX_PROBLEMS = 5
#: Most characters of a bad value an error line repeats.
MAX_VALUE_CHARS = 60


def one_line(problems: list[str], limit: int = MAX_PROBLEMS) -> str:
    """`problems` joined by ``; ``, the first `limit` of them and how many more there are."""
    shown = "; ".join(problems[:limit])
    more = len(problems) - limit
    return shown + (f"; and {more} more problem{'s' * (more > 1)}" if more > 0 else "")


def short_repr(value: object, limit: int = MAX_VALUE_CHARS) -> str:
    """``repr(value)``, cut to `limit` characters with an ellipsis."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def few(names: list[str] | set[str], limit: int = MAX_PROBLEMS) -> str:
    """Sorted `names` as a list literal, the first `limit` of them and how many there are."""
    items = sorted(names)
    if len(items) <= limit:
        return repr(items)
    return repr(items[:limit])[:-1] + f", ... ({len(items)} in all)]"
