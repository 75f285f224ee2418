"""The project's one root exception and its located subclasses.

Every problem a user can cause (a bad model, a DSL syntax error, a dangling reference, an
impossible selection) is an `RraError`. Problems tied to a place in a file are `LocatedError`s
and render as ``file:line:col: message`` so editors and terminals can jump to them. The CLI
catches `RraError` and prints it without a traceback.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Location:
    """A 1-based position in a source file."""

    file: str
    line: int
    col: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.col}"


class RraError(Exception):
    """Root of every error rra-agent reports to a user."""


class LocatedError(RraError):
    """An error at a position in a model or DSL file.

    `source_line`, when known, is the text of the offending line; `str()` then adds it with a
    caret under the column, the way compilers do.
    """

    def __init__(
        self, message: str, location: Location | None, *, source_line: str | None = None
    ) -> None:
        self.message = message
        self.location = location
        self.source_line = source_line
        super().__init__(self.render())

    @property
    def headline(self) -> str:
        """``file:line:col: message`` (or just the message when the place is unknown)."""
        return f"{self.location}: {self.message}" if self.location else self.message

    def render(self) -> str:
        if self.source_line is None or self.location is None:
            return self.headline
        caret = " " * max(self.location.col - 1, 0) + "^"
        return f"{self.headline}\n    {self.source_line.rstrip()}\n    {caret}"


class ModelError(LocatedError):
    """A model file is malformed: wrong type, unknown field, bad value, dangling reference."""


class DslSyntaxError(LocatedError):
    """A UVL or rule-DSL text does not parse; `expected` lists the tokens that would have."""

    def __init__(
        self,
        message: str,
        location: Location | None,
        *,
        expected: Sequence[str] = (),
        source_line: str | None = None,
    ) -> None:
        self.expected = tuple(expected)
        super().__init__(message, location, source_line=source_line)


class SemanticError(LocatedError):
    """A text parses but means something impossible (unknown name, equal priorities, ...)."""


class ResolutionError(RraError):
    """Transformations cannot be applied: conflicting values, missing targets."""


class SelectionError(RraError):
    """A feature selection is impossible for the feature model (with the reasons)."""

    def __init__(self, message: str, reasons: Sequence[str] = ()) -> None:
        self.reasons = tuple(reasons)
        text = message if not reasons else message + "\n" + "\n".join(f"  - {r}" for r in reasons)
        super().__init__(text)


class ErrorGroup(RraError):
    """Several independent errors found in one pass (e.g. by ``rra validate``)."""

    def __init__(self, errors: Iterable[RraError]) -> None:
        self.errors: list[RraError] = list(errors)
        super().__init__("\n".join(str(e) for e in self.errors))

    @staticmethod
    def raise_if_any(errors: Sequence[RraError]) -> None:
        """Raise the single error itself, a group for several, nothing for none."""
        if len(errors) == 1:
            raise errors[0]
        if errors:
            raise ErrorGroup(errors)
