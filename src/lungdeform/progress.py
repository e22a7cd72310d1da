"""Progress reporting: the one type of every ``progress`` parameter, and the default that says nothing.

A long step (a fit, a cohort, an export) tells its caller what it is doing through a
:class:`Progress`: a callable taking one message line (``"right: fitting the direction"``). Library
code never prints (docs/ARCHITECTURE.md); the CLI passes :func:`lungdeform.cli.common.say`, which
writes to stderr. A function taking ``progress: Progress | None`` uses ``progress or silent``.
This module sits in the lowest layer beside :mod:`lungdeform.errors` and imports nothing of the package.
"""

from __future__ import annotations

from typing import Protocol


class Progress(Protocol):
    """Receives one progress message (a line of text, no newline)."""

    def __call__(self, message: str, /) -> None: ...


def silent(message: object, /) -> None:
    """A :class:`Progress` that says nothing: the default where no ``progress`` is given."""
