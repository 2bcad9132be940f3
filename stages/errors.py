"""The one error type markcal raises for a user's mistake."""
from __future__ import annotations


class MarkcalError(Exception):
    """Bad input: names the file (when there is one) and what is wrong.

    Parameters
    ----------
    message : str
        What is wrong, in one line.
    path : str or os.PathLike, optional
        The file the problem is in.
    """

    def __init__(self, message: str, path=None):
        self.path = None if path is None else str(path)
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path else message)

    def with_path(self, path) -> "MarkcalError":
        """Return the same error naming ``path`` (if it names no file yet)."""
        return self if self.path else MarkcalError(self.message, path)


def one_line(exc: BaseException, max_chars: int = 400) -> str:
    """A one-line reason for an exception: a MarkcalError's text as is, else its type and message."""
    if isinstance(exc, MarkcalError):
        text = str(exc)
    else:
        text = f"internal error: {type(exc).__name__}: {exc}"
    text = " ".join(text.split())
    return text[:max_chars] + ("…" if len(text) > max_chars else "")
