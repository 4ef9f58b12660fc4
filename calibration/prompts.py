"""Answers from options, or from the user at a terminal.

Non-interactive (stdin is not a TTY: CI, scripts, pipes): every answer must come as an option; a missing
one raises MissingAnswerError naming the option. Interactive: a missing answer is asked for on the terminal
until it converts (the conversion's error is shown and the question repeated).
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


class MissingAnswerError(ValueError):
    """A required option is missing and there is no terminal to ask on."""


def interactive() -> bool:
    """True when stdin is a terminal (the wizard may prompt)."""
    try:
        return sys.stdin.isatty()
    except (AttributeError, ValueError):
        return False


def answer(
    value: T | None,
    option: str,
    question: str,
    convert: Callable[[str], T],
    default: T | None = None,
    ask: Callable[[str], str] | None = None,
) -> T:
    """`value` if given; else the user's converted answer at a terminal (empty → `default` if not None);
    else `default` if not None; else MissingAnswerError."""
    if value is not None:
        return value
    if not interactive():
        if default is not None:
            return default
        raise MissingAnswerError(
            f"{option} is required (no terminal to ask on: pass every answer as an option in scripts and CI)"
        )
    ask = ask or input  # looked up at call time (tests replace builtins.input)
    suffix = f" [{default}]" if default is not None else ""
    while True:
        text = ask(f"{question}{suffix}: ").strip()
        if not text and default is not None:
            return default
        try:
            return convert(text)
        except ValueError as exc:
            print(f"  {exc}", file=sys.stderr)


def positive_float(text: str) -> float:
    v = float(text)
    if not (v > 0 and math.isfinite(v)):
        raise ValueError(f"a finite positive number is required, got {text!r}")
    return v


def positive_int(text: str) -> int:
    v = int(text)
    if v <= 0:
        raise ValueError(f"a positive integer is required, got {text!r}")
    return v


def choice(options: tuple[str, ...]) -> Callable[[str], str]:
    def convert(text: str) -> str:
        if text not in options:
            raise ValueError(f"one of {', '.join(options)} is required, got {text!r}")
        return text

    return convert
