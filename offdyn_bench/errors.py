"""Errors a person can act on: what was wrong, what was expected, the closest valid names."""

from __future__ import annotations

import contextlib
import difflib
from collections.abc import Iterable, Iterator


class OffdynError(ValueError):
    """Base class of every error this suite raises on bad input."""


class UnknownNameError(OffdynError, KeyError):
    """A name (task, effect kind, body, joint, ...) that does not exist."""

    def __init__(self, what: str, name: object, valid: Iterable[str]) -> None:
        self.what = what
        self.name = name
        self.valid = sorted(set(valid))
        close = difflib.get_close_matches(str(name), self.valid, n=5, cutoff=0.5)
        if close:
            hint = "closest valid names: " + ", ".join(repr(c) for c in close)
        elif len(self.valid) <= 12:
            hint = "valid names: " + ", ".join(repr(v) for v in self.valid)
        else:
            hint = f"{len(self.valid)} valid names, e.g. " + ", ".join(repr(v) for v in self.valid[:6])
        super().__init__(f"unknown {what} {name!r}; {hint}")

    # KeyError would otherwise print the message wrapped in quotes.
    def __str__(self) -> str:
        return str(self.args[0])


class InvalidParameterError(OffdynError):
    """A parameter outside its valid range."""

    def __init__(self, owner: str, parameter: str, value: object, expected: str) -> None:
        self.owner = owner
        self.parameter = parameter
        self.value = value
        super().__init__(f"{owner}: invalid {parameter}={value!r}; expected {expected}")


@contextlib.contextmanager
def exit_on_error() -> Iterator[None]:
    """For a command-line command: an :class:`OffdynError` becomes one ``error: ...`` line on
    stderr and exit code 2, never a traceback."""
    import typer

    try:
        yield
    except OffdynError as error:
        typer.echo(f"error: {error}", err=True)
        raise typer.Exit(2) from None
