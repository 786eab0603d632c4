"""argparse ``type=`` converters for numeric options: a bad value is one line, exit 2.

:func:`output` and :func:`not_for` are ``action=``s refusing the same way as the command line
is parsed, before anything runs: an output path that cannot be written, an option that does
not apply.

``physical`` bounds magnitudes to [1e-150, 1e150] (or 0) so that products and quotients of two
values stay finite and normal in double precision (1e308 overflowed (11.6)-(11.7), 1e-320 is
subnormal and divided by zero).
"""

from __future__ import annotations

import argparse
import math
from typing import Any, Callable

#: Largest and smallest non-zero magnitude accepted by ``physical``.
MAX_MAGNITUDE, MIN_MAGNITUDE = 1e150, 1e-150


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be finite, got {text!r}")
    return value


def physical(text: str) -> float:
    """A finite float of physical magnitude (0, or |x| in [1e-150, 1e150])."""
    value = _float(text)
    if value != 0 and not MIN_MAGNITUDE <= abs(value) <= MAX_MAGNITUDE:
        raise argparse.ArgumentTypeError(
            f"{text} is outside [{MIN_MAGNITUDE:g}, {MAX_MAGNITUDE:g}] in magnitude "
            f"(double precision overflows or underflows)"
        )
    return value


def positive(text: str) -> float:
    """A physical float > 0."""
    value = physical(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def non_negative(text: str) -> float:
    """A physical float >= 0."""
    value = physical(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be >= 0, got {text}")
    return value


def probability(text: str) -> float:
    """A float in [0, 1]."""
    value = _float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be a probability in [0, 1], got {text}")
    return value


def int_range(lo: int, hi: int) -> Callable[[str], int]:
    """An integer in [lo, hi]."""

    def convert(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be in [{lo}, {hi}], got {value}")
        return value

    return convert


#: TCP port: 0 (any free one) to 65535.
port = int_range(0, 65535)


class _Refusing(argparse.Action):
    """An option refused, when :meth:`why` says why, as argparse refuses: ``OPTION WHY``, one
    line, exit 2, while the command line is parsed."""

    def why(self, values: Any) -> str:
        return ""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        why = self.why(values)
        if why:
            parser.error(f"{option_string or self.metavar or self.dest} {why}")
        setattr(namespace, self.dest, values)


def output(kind: str = "file") -> type[argparse.Action]:
    """The argparse ``action=`` of an output path (``kind`` file, folder or bag, as
    :func:`piezo_stage.config_path.output_problem` checks them): a path that cannot be written
    is refused while the command line is parsed, before anything runs, in one line naming the
    option (``--bag b: folder already exists and is not empty``), exit 2."""
    from piezo_stage.config_path import OUTPUT_KINDS, output_problem

    if kind not in OUTPUT_KINDS:
        raise ValueError(f"kind must be one of {', '.join(OUTPUT_KINDS)}, got {kind!r}")

    class Output(_Refusing):
        def why(self, values: Any) -> str:
            problem = output_problem(values, kind)
            return f"{values}: {problem}" if problem else ""

    return Output


def not_for(what: str) -> type[argparse.Action]:
    """The argparse ``action=`` of an option that ``what`` (e.g. ``experiment raster``) does
    not take: refused in one line, ``--axis does not apply to experiment raster``, exit 2."""

    class NotHere(_Refusing):
        def why(self, values: Any) -> str:
            return f"does not apply to {what}"

    return NotHere


def data_error_exit_code(exc: Exception) -> int:
    """Exit code of `identify`/`validate` for an error raised while reading or identifying:
    2 for unusable input (unreadable, non-finite, out of range, too short, clipped, a bad
    parameter file), 1 when the data were read but do not support the identification."""
    from piezo_stage.identification.errors import IdentificationError, InputDataError

    if isinstance(exc, IdentificationError) and not isinstance(exc, InputDataError):
        return 1
    return 2


def bag_error_exit_code(exc: Exception) -> int:
    """Exit code for an error opening or reading a bag: 1 for a damaged bag, 2 for input that is
    not usable at all (no such path, not a bag, a topic the bag does not hold)."""
    from piezo_stage.bag.errors import CorruptBagError

    return 1 if isinstance(exc, CorruptBagError) else 2
