"""Frame-range command-line arguments, after OpenUSD's `UsdAppUtils.framesArgs`.

usd-core ships without `UsdAppUtils`, so this module reproduces its conventions:

- `--frames/-f FRAMESPEC[,FRAMESPEC...]` and `--defaultTime/-d` are mutually exclusive;
  with neither, the command works at the stage's earliest time code.
- A FrameSpec is one time code (`123`), a range (`101:105`, also written `101-105`) or a
  range with a stride (`101:109x2`, `1-100x2`, `101:104x0.5`); ranges may run backwards.
- With `--frames`, the output path must hold exactly one frame placeholder (`####` or
  `###.##`) with at least the precision the strides need; without it, it must hold none.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass

from pxr import Usd, UsdUtils

__all__ = [
    "FrameSpecError",
    "FrameSpecIterator",
    "add_cmdline_args",
    "convert_frame_placeholder_to_float_spec",
    "get_frame_placeholder",
    "validate_cmdline_args",
]

_NUMBER = r"[+-]?(?:\d+(?:\.\d*)?|\.\d+)"
#: start, optionally `:` or `-` end, optionally `x` stride. The `-` form is what farm
#: schedulers write; a leading sign still makes a negative frame (`-5--1`).
_FRAME_SPEC = re.compile(rf"^\s*({_NUMBER})(?:\s*[:-]\s*({_NUMBER})(?:\s*x\s*({_NUMBER}))?)?\s*$")
_PLACEHOLDER = re.compile(r"#+(?:\.#+)?")


class FrameSpecError(ValueError):
    """A FrameSpec or frame placeholder that cannot be used; the message says why."""


def _float_string_precision(text: str | None) -> int:
    if not text:
        return 0
    parts = text.split(".")
    return len(parts[1]) if len(parts) > 1 else 0


@dataclass(frozen=True)
class _Range:
    start: float
    end: float
    stride: float

    def time_codes(self) -> Iterator[Usd.TimeCode]:
        spec = f"{self.start!r}:{self.end!r}x{self.stride!r}"
        # UsdUtils.TimeCodeRange does the stepping, so rounding matches usdrecord exactly.
        yield from UsdUtils.TimeCodeRange.CreateFromFrameSpec(spec)


class FrameSpecIterator:
    """Iterates the time codes of comma-separated FrameSpecs, in the order given.

    `min_float_precision` is the number of decimals that the strides need, so that a frame
    placeholder can be checked to tell every frame apart.
    """

    SEPARATOR = ","

    def __init__(self, frame_spec: str) -> None:
        self._ranges: list[_Range] = []
        self.min_float_precision = 0
        if not frame_spec.strip():
            raise FrameSpecError("the frame range is empty")
        for part in frame_spec.split(self.SEPARATOR):
            match = _FRAME_SPEC.match(part)
            if match is None:
                raise FrameSpecError(
                    f"invalid FrameSpec {part.strip()!r}: expected a frame (12), a range "
                    "(1-100 or 1:100) or a range with a stride (1-100x2)"
                )
            start_text, end_text, stride_text = match.groups()
            start = float(start_text)
            end = float(end_text) if end_text is not None else start
            if stride_text is None:
                stride = 1.0 if end >= start else -1.0
            else:
                stride = abs(float(stride_text))
                if stride == 0.0:
                    raise FrameSpecError(f"invalid FrameSpec {part.strip()!r}: stride is 0")
                if end < start:
                    stride = -stride
                self.min_float_precision = max(
                    self.min_float_precision, _float_string_precision(stride_text)
                )
            self._ranges.append(_Range(start, end, stride))

    def __iter__(self) -> Iterator[Usd.TimeCode]:
        for frame_range in self._ranges:
            yield from frame_range.time_codes()

    def frames(self) -> list[float]:
        """The time codes as floats."""
        return [code.GetValue() for code in self]


def get_frame_placeholder(frame_format: str | None) -> str | None:
    """The single `###` or `###.##` placeholder in `frame_format`, or None if it has none.

    Raises `FrameSpecError` if hashes are there but do not form exactly one placeholder.
    """
    if not frame_format or "#" not in frame_format:
        return None
    matches = _PLACEHOLDER.findall(frame_format)
    if len(matches) != 1 or frame_format.count("#") != matches[0].count("#"):
        raise FrameSpecError(
            f"{frame_format!r} must hold exactly one frame placeholder of the form "
            "'####' or '###.##'"
        )
    return str(matches[0])


def convert_frame_placeholder_to_float_spec(frame_format: str) -> str | None:
    """`frame_format` with its placeholder turned into a `{frame:0W.Pf}` field, or None.

    The placeholder's full width is the zero-padded minimum width; hashes after the dot
    are the decimals. Braces elsewhere in the path are escaped.
    """
    placeholder = get_frame_placeholder(frame_format)
    if placeholder is None:
        return None
    precision = _float_string_precision(placeholder)
    head, tail = frame_format.split(placeholder)
    escape = lambda text: text.replace("{", "{{").replace("}", "}}")  # noqa: E731
    return f"{escape(head)}{{frame:0{len(placeholder)}.{precision}f}}{escape(tail)}"


def add_cmdline_args(parser: argparse.ArgumentParser) -> None:
    """Adds the mutually exclusive `--defaultTime/-d` and `--frames/-f` arguments."""
    group = parser.add_mutually_exclusive_group()
    group.add_argument(
        "--defaultTime",
        "-d",
        action="store_true",
        dest="defaultTime",
        help="operate at the Default time code (without it: the earliest time code)",
    )
    group.add_argument(
        "--frames",
        "-f",
        dest="frames",
        metavar="FRAMESPEC[,FRAMESPEC...]",
        help=(
            "time codes to render: a frame (12), a range (1-100 or 1:100), a range with a "
            "stride (1-100x2, 101:104x0.5), or a comma-separated list of these (1,5,9)"
        ),
    )


@dataclass(frozen=True)
class FrameArgs:
    """What `validate_cmdline_args` resolves: the time codes and the output formats."""

    time_codes: list[Usd.TimeCode]
    #: Each frame-format argument as a `str.format(frame=...)` template (or unchanged).
    formats: dict[str, str]


def validate_cmdline_args(
    args: argparse.Namespace, frame_format_arg_names: Sequence[str] = ()
) -> FrameArgs:
    """Resolves `--frames`/`--defaultTime` and checks the frame placeholders.

    Raises `FrameSpecError` (the caller turns it into a usage error) when a FrameSpec is
    invalid, a frame-format argument lacks a placeholder while a range is given, has one
    without a range, or has too few decimals for the strides.
    """
    formats: dict[str, str] = {}
    if args.frames is not None:
        frames = FrameSpecIterator(args.frames)
        time_codes = list(frames)
        if not time_codes:
            raise FrameSpecError(f"the frame range {args.frames!r} holds no frames")
    else:
        frames = None
        time_codes = [Usd.TimeCode.Default() if args.defaultTime else Usd.TimeCode.EarliestTime()]
    for name in frame_format_arg_names:
        value = getattr(args, name)
        if value is None:
            continue
        option = "--" + name.replace("_", "-")
        placeholder = get_frame_placeholder(value)
        if frames is None:
            if placeholder is not None:
                raise FrameSpecError(
                    f"{option} {value!r} has a frame placeholder, but no --frames were given"
                )
            formats[name] = value
            continue
        template = convert_frame_placeholder_to_float_spec(value)
        if placeholder is None or template is None:
            raise FrameSpecError(
                f"{option} {value!r} must hold exactly one frame placeholder such as '####' "
                "when rendering --frames"
            )
        if _float_string_precision(placeholder) < frames.min_float_precision:
            raise FrameSpecError(
                f"the FrameSpecs need {frames.min_float_precision} decimal(s), but the "
                f"placeholder {placeholder!r} of {option} has "
                f"{_float_string_precision(placeholder)}; use e.g. "
                f"'####.{'#' * frames.min_float_precision}'"
            )
        formats[name] = template
    return FrameArgs(time_codes=time_codes, formats=formats)
