"""Option value types: every invalid value is a usage error (exit 2) naming the valid form.

The parsers live in ``stages`` (they serve files and batch parameters too) and raise
:class:`~stages.errors.InputError`; these types turn that into click's usage error.
"""

from __future__ import annotations

import math
from typing import Any

import click

from stages.errors import InputError


class MotionSpec(click.ParamType):
    """A motion SPEC, checked by :func:`stages.motion.parse_motion`; the value stays text.

    ``field:PATH`` is checked for its form only: reading the file is the command's work
    (a missing or wrong file is a runtime error, exit 1).
    """

    name = "SPEC"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        from stages.motion import parse_motion

        text = str(value)
        if text.strip().startswith("field:"):
            if not text.strip()[len("field:") :]:
                self.fail("field:PATH needs the path of a motion file", param, ctx)
            return text
        try:
            parse_motion(text)
        except InputError as exc:
            self.fail(str(exc), param, ctx)
        return text


class Size(click.ParamType):
    """``WxH`` in pixels, returned as ``(width, height)`` (:func:`stages.scenes.parse_size`)."""

    name = "WxH"

    def get_metavar(self, *args: Any, **kwargs: Any) -> str:
        return "WxH"

    def convert(
        self, value: Any, param: click.Parameter | None, ctx: click.Context | None
    ) -> tuple[int, int]:
        from stages.scenes import parse_size

        if isinstance(value, tuple):
            return value
        try:
            return parse_size(str(value))
        except InputError as exc:
            self.fail(str(exc), param, ctx)


class FiniteFloatRange(click.FloatRange):
    """:class:`click.FloatRange` that also refuses ``nan`` and ``inf``."""

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        rv = super().convert(value, param, ctx)
        if rv is not None and not math.isfinite(rv):
            self.fail(f"{value!r} is not a finite number", param, ctx)
        return rv


def positive() -> FiniteFloatRange:
    """A finite float > 0."""
    return FiniteFloatRange(min=0, min_open=True)


def non_negative() -> FiniteFloatRange:
    """A finite float >= 0."""
    return FiniteFloatRange(min=0)


class SchedulerAddress(click.ParamType):
    """A Dask scheduler's address, ``tcp://HOST:PORT`` (or ``HOST:PORT``), checked for
    its form before anything is contacted (:func:`stages.cluster.parse_scheduler_address`)."""

    name = "ADDRESS"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        from stages.cluster import parse_scheduler_address

        try:
            return parse_scheduler_address(str(value))
        except InputError as exc:
            self.fail(str(exc), param, ctx)


class Timeout(click.ParamType):
    """Seconds (a finite number > 0), ``auto`` (kept as text) or ``none`` (None)."""

    name = "SECONDS|auto|none"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if value is None or isinstance(value, int | float):
            return value
        text = str(value).strip().lower()
        if text in ("auto", "none"):
            return None if text == "none" else "auto"
        try:
            seconds = float(text)
        except ValueError:
            seconds = math.nan
        if not (math.isfinite(seconds) and seconds > 0):
            self.fail(f"{value!r}: give a number of seconds > 0, auto or none", param, ctx)
        return seconds


MOTION = MotionSpec()
SCHEDULER = SchedulerAddress()
TIMEOUT = Timeout()
SIZE = Size()
#: Noise seeds: numpy's generators take non-negative integers.
SEED = click.IntRange(min=0)
#: Exposure shifts in stops (stages.tonemap's range).
STOPS = FiniteFloatRange(-64, 64)


class MeasureBins(click.ParamType):
    """``all`` (every measuring subframe, the default: returned as None) or a number of
    time bins from 0 (none) to 1000."""

    name = "all|N"

    def get_metavar(self, *args: Any, **kwargs: Any) -> str:
        return "all|N"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None):
        if value is None or (isinstance(value, str) and value.strip().lower() == "all"):
            return None
        try:
            n = int(str(value).strip())
        except ValueError:
            self.fail(
                f"{value!r} is not 'all' or a whole number of bins from 0 to 1000", param, ctx
            )
        if not 0 <= n <= 1000:
            self.fail(f"{n} bins: allowed 'all' or 0 to 1000", param, ctx)
        return n
