"""Typed exceptions raised at the public boundary of gpdepth3d.

Every error raised on bad user input names the argument, what was expected and what came,
so that the CLI can print it on one line and a caller can catch it by type.
"""

from __future__ import annotations

from typing import Any


class GPDepthError(Exception):
    """Base class of every error gpdepth3d raises on purpose."""


class InvalidInputError(GPDepthError, ValueError):
    """An argument has the wrong type, shape, range or content.

    Attributes:
        argument: Name of the offending argument.
        expected: What was expected, in words.
        got: What came, in words.
    """

    def __init__(self, argument: str, expected: str, got: Any):
        self.argument = argument
        self.expected = expected
        self.got = got
        super().__init__(f"{argument}: expected {expected}, got {got}")

    def __reduce__(self):  # picklable (Dask workers, multiprocessing) with its attributes
        return (type(self), (self.argument, self.expected, self.got))


class ShapeError(InvalidInputError):
    """An array has the wrong shape or two arrays do not fit together."""


class InvalidDepthError(InvalidInputError):
    """A depth array holds values that break the stated convention (NaN, inf, negative...)."""


class CalibrationError(InvalidInputError):
    """Intrinsics, extrinsics or a pose do not fit the data (or are not a valid transform)."""


class EmptyInputError(InvalidInputError):
    """An input that must hold at least one valid element holds none."""


class DataFormatError(GPDepthError, ValueError):
    """A file is missing, of an unknown format, or corrupt."""

    def __init__(self, path: Any, problem: str):
        self.path = path
        self.problem = problem
        super().__init__(f"{path}: {problem}")

    def __reduce__(self):
        return (type(self), (self.path, self.problem))


class OutputError(GPDepthError, OSError):
    """An output cannot be written: a read-only folder, a full disk, a directory or a file in the way.

    Attributes:
        path: The output that could not be written.
        problem: What went wrong, in words.
    """

    def __init__(self, path: Any, problem: str):
        self.path = path
        self.problem = problem
        super().__init__(f"{path}: cannot write: {problem}")

    def __str__(self) -> str:
        return f"{self.path}: cannot write: {self.problem}"

    def __reduce__(self):  # picklable across Dask workers
        return (type(self), (self.path, self.problem))


class ConnectionFailedError(GPDepthError, ConnectionError):
    """A server (a Dask scheduler) could not be reached within the time allowed.

    Attributes:
        address: The address tried.
        problem: What went wrong, in words.
    """

    def __init__(self, address: Any, problem: str):
        self.address = address
        self.problem = problem
        super().__init__(f"{address}: {problem}")

    def __reduce__(self):
        return (type(self), (self.address, self.problem))


class ProblemTooLargeError(GPDepthError, MemoryError):
    """A problem exceeds the size an engine accepts (for example the dense `exact` engine)."""

    def __reduce__(self):
        # an explicit reduction: tblib's exception pickling (installed by Dask's workers) otherwise
        # rebuilds it with MemoryError.__new__, which refuses subclasses
        return (type(self), self.args)


class ConvergenceError(GPDepthError, ArithmeticError):
    """An iterative solver (conjugate gradients) did not reach its tolerance within its iteration limit."""


def describe(x: Any) -> str:
    """Short description of a value for an error message (shape and dtype of arrays)."""
    shape = getattr(x, "shape", None)
    dtype = getattr(x, "dtype", None)
    if shape is not None:
        return f"array of shape {tuple(shape)} and dtype {dtype}"
    return f"{type(x).__name__} {x!r}"[:200]


def did_you_mean(word: str, choices: Any) -> str:
    """``" (did you mean X?)"`` for the choice closest to a mistyped ``word``, or ``""`` when none is close."""
    import difflib

    close = difflib.get_close_matches(str(word), [str(c) for c in choices], n=1, cutoff=0.6)
    return f" (did you mean {close[0]}?)" if close else ""
