"""What every `shadowopt` subcommand module shares: the usage exit code, CliError (a one-line reason, exit 2) and
the WxH argument type."""
from __future__ import annotations

import argparse

EXIT_USAGE = 2


class CliError(Exception):
    def __init__(self, message: str, code: int = EXIT_USAGE):
        super().__init__(message)
        self.code = code


def parse_wxh(text: str) -> list[int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
        return [w, h]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH with positive integers, got {text!r}") from None
