"""Errors a user can act on.

Every problem with the user's input (a capture, an output directory, a
setting) raises :class:`InputError`. The CLI prints its message as one line
and exits with status 2; nothing already written is touched.
"""
from __future__ import annotations

from pathlib import Path


class InputError(Exception):
    """A problem with the user's input: one clear line naming the file and the problem."""

    def __init__(self, message: str, path: str | Path | None = None):
        self.path = None if path is None else Path(path)
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)


class TooFewLinesError(InputError):
    """The scene has too few (Manhattan) line segments to reconstruct."""


class OnlyVerticalEdgesError(TooFewLinesError):
    """The frames show vertical edges only (a bare room): no horizontal Manhattan direction, no line-fixed frame."""
