"""One exception type for bad user input, so the CLI can print one line and exit 2."""

import math
import numbers


class ConfigError(ValueError):
    """A parameter value outside what is allowed; the message names both."""


def bad_value(name: str, value: object, allowed: str) -> ConfigError:
    """Build the one-line error every entry point uses: parameter, value, what is allowed (a value whose repr
    spans lines, a long array's, is put on one)."""
    return ConfigError(f"invalid {name}={' '.join(repr(value).split())}: {allowed}")


def check_instance(name: str, value: object, kind: type, allowed: str) -> None:
    """One error line unless `value` is a `kind` (`allowed` says what is, and how to make one), rather than an
    AttributeError from deep inside whatever first reads it."""
    if not isinstance(value, kind):
        raise bad_value(name, value, f"must be {allowed}")


def one_line(err: BaseException) -> str:
    """`Type: message` of an exception on one line (torch's `load_state_dict` message spans several)."""
    return f"{type(err).__name__}: {' '.join(str(err).split())}"


def plural(n: int, one: str, many: str, grouped: bool = False) -> str:
    """`1 episode`, `2 episodes`: a count in a message, as a reader says it (`grouped`: `25,000 episodes`)."""
    return f"{n:,} {one if n == 1 else many}" if grouped else f"{n} {one if n == 1 else many}"


def os_error_line(err: OSError) -> str:
    """What the system refused, on one line: the file, if the error names one, then why (`[Errno 28] No space
    left on device: 'x'` without the number, which tells a user nothing the words do not)."""
    why = err.strerror or " ".join(str(err).split()) or type(err).__name__
    return f"{str(err.filename)!r}: {why}" if err.filename is not None else why


def check_int(name: str, value: object, least: int) -> None:
    """One error line unless `value` is an integer >= `least` (a bool or 2.5 is not; `name` as a flag)."""
    if not is_integer(value) or value < least:  # type: ignore[operator]
        raise bad_value(name.replace("_", "-"), value, f"must be an integer >= {least}")


def is_integer(value: object) -> bool:
    """A Python or numpy integer that is not a bool (True is an int to Python, never a count here)."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


def is_number(value: object) -> bool:
    """A real number that is not a bool (an int counts; NaN is one, and fails every bound)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def check_number(name: str, value: object, least: float, strict: bool = False, finite: bool = True) -> None:
    """One error line unless `value` is a number >= `least` (> with `strict`; NaN never is), and finite
    unless `finite` is False: an infinite rate or interval is never what a user meant."""
    bound = f"{'>' if strict else '>='} {least:g}"
    if not (is_number(value) and (value > least if strict else value >= least)):  # type: ignore[operator]
        raise bad_value(name.replace("_", "-"), value, f"must be a {'finite ' if finite else ''}number {bound}")
    if finite and not math.isfinite(value):  # type: ignore[arg-type]
        raise bad_value(name.replace("_", "-"), value, f"must be a finite number {bound}")


FLOAT32_MAX = 3.4028234663852886e38


def check_rate(name: str, value: object) -> None:
    """A learning rate: a number > 0 that float32 holds (the optimizers step in float32; a larger one is a
    traceback from inside Adam, not a run that diverges)."""
    check_number(name, value, 0.0, strict=True)
    if value > FLOAT32_MAX:  # type: ignore[operator]
        raise bad_value(name.replace("_", "-"), value, f"must be at most {FLOAT32_MAX:.4g}, the largest float32")
