"""Typed errors. Every failure names what is at fault: file, row, column, joint or frame."""

from __future__ import annotations

import numpy as np


class M3t1rError(Exception):
    """Base class of every error raised by m3t1r."""


class ModelFileError(M3t1rError):
    """A model file (URDF or closures YAML) is missing, unreadable or inconsistent."""

    def __init__(self, path: object, message: str) -> None:
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


class InvalidInputError(M3t1rError, ValueError):
    """A numeric input is malformed: NaN/inf, wrong length, or outside its joint's limits."""


class KinematicsError(M3t1rError):
    """A closed-loop solve failed. Carries the final residual norm and iteration count."""

    def __init__(self, message: str, residual: float = float("nan"), iterations: int = 0) -> None:
        self.residual = float(residual)
        self.iterations = int(iterations)
        super().__init__(f"{message} (residual {self.residual:.3e} after {self.iterations} iterations)")


class NotConvergedError(KinematicsError):
    """Newton did not bring the residual below tolerance."""


class SingularConfigurationError(KinematicsError):
    """The Jacobian of the square system is singular (or nearly) at the solution or on the way."""


class BranchChangeError(KinematicsError):
    """Newton crossed a singularity: the solution is on another assembly or working mode than the start."""


class OutOfWorkspaceError(KinematicsError):
    """The target cannot be reached: no assembly, or the solution needs a slider beyond its limit."""


class DataFileError(M3t1rError):
    """A CSV input is malformed; names the file, row (1-based line number) and column at fault."""

    def __init__(self, path: object, message: str, row: int | None = None, column: str | None = None) -> None:
        self.path = str(path)
        self.row = row
        self.column = column
        where = self.path
        if row is not None:
            where += f", line {row}"
        if column is not None:
            where += f", column '{column}'"
        super().__init__(f"{where}: {message}")


class IdentificationError(M3t1rError):
    """Identification cannot proceed: too few poses, rank-deficient data, divergence."""


def real_array(values: object, what: str, expected: str = "numeric") -> np.ndarray:
    """`values` as a float array, or InvalidInputError naming `what`. Complex values are refused,
    not cut to their real part as numpy's float conversion does (0.1+1j would read as 0.1)."""
    try:
        complex_given = np.iscomplexobj(np.asarray(values))
    except (TypeError, ValueError):
        complex_given = False  # ragged or odd input: the float conversion below names it
    if complex_given:
        raise InvalidInputError(f"{what}: complex values given; joint values and coordinates are real numbers")
    try:
        return np.asarray(values, dtype=float)
    except (TypeError, ValueError) as exc:
        raise InvalidInputError(f"{what}: not {expected} ({exc})") from None


def require_finite_vector(values: object, length: int, what: str) -> np.ndarray:
    """Return `values` as a float vector of `length`, or raise InvalidInputError naming `what`
    (complex, NaN and infinite values refused)."""
    vector = real_array(values, what, "a numeric vector").reshape(-1)
    if vector.size != length:
        raise InvalidInputError(f"{what}: expected {length} values, got {vector.size}")
    finite = np.isfinite(vector)
    if not finite.all():
        bad = np.flatnonzero(~finite)
        raise InvalidInputError(f"{what}: non-finite value {vector[bad[0]]} at index {bad[0]}")
    return vector


def require_real(value: object, what: str, *, minimum: float = -np.inf, inclusive: bool = True) -> float:
    """`value` as a finite float at least (or, not inclusive, above) `minimum`, else InvalidInputError
    naming `what`. Booleans, complex numbers, NaN and infinities are refused."""
    if isinstance(value, (bool, np.bool_, complex, np.complexfloating, str, bytes)):
        raise InvalidInputError(f"{what}: expected a real number, got {value!r}")
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InvalidInputError(f"{what}: expected a real number, got {value!r}") from None
    if not np.isfinite(number) or number < minimum or (not inclusive and number == minimum):
        bound = f" {'at least' if inclusive else 'above'} {minimum:g}" if np.isfinite(minimum) else ""
        raise InvalidInputError(f"{what}: expected a finite number{bound}, got {value!r}")
    return number


def require_count(value: object, what: str, minimum: int = 1) -> int:
    """`value` as an int of at least `minimum` (an integral float such as 3.0 is accepted), else
    InvalidInputError naming `what`."""
    if (
        isinstance(value, (bool, np.bool_))
        or not isinstance(value, (int, np.integer, float, np.floating))
        or not float(value).is_integer()
        or int(value) < minimum
    ):
        raise InvalidInputError(f"{what}: expected a whole number of at least {minimum}, got {value!r}")
    return int(value)


class OutputPathError(M3t1rError):
    """An output cannot be written: the path is a protected input, is not a file path, or the write failed."""

    def __init__(self, path: object, message: str) -> None:
        self.path = str(path)
        super().__init__(f"{self.path}: {message}")


class UnknownNameError(InvalidInputError):
    """A joint or frame name does not exist in the model (names are matched exactly)."""

    def __init__(self, kind: str, name: str, message: str = "") -> None:
        self.kind = kind
        self.name = name
        super().__init__(f"{kind} '{name}': {message or 'not found in the model'}")


class UnsupportedJointError(InvalidInputError):
    """A joint cannot be used where it is needed (e.g. a multi-DoF joint inside a serial POE chain)."""

    def __init__(self, joint: str, message: str) -> None:
        self.joint = joint
        super().__init__(f"joint '{joint}': {message}")


class PoorExcitationWarning(UserWarning):
    """The pose set barely excites some kept parameters: their estimates will be noise-dominated."""


class ModelWarning(UserWarning):
    """`Mechanism.load` changed or assumed something about the files (see `Mechanism.notes`)."""


class MissingExtraError(M3t1rError):
    """An optional reader needs a package that is not installed; names the pip extra that brings it."""
