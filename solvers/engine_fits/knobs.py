"""What a user can set on an engine's own shadows: one Knob per option, and the one validation every engine's
module runs (solvers.engine_fits: the interface)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

KINDS = ("int", "float", "choice", "bool")


@dataclass(frozen=True)
class Knob:
    """One engine option, under the engine's own name (the key in the engine module's KNOBS).

    default: the engine's own default (what it uses when the option is not given);
    kind: "int" | "float" | "choice" | "bool";
    domain: for "int" / "float" the inclusive range (lo, hi); for "choice" / "bool" the tuple of accepted values
            (an engine value the emulation does not model is left out of it, and the knob's doc says so);
    doc: one line for users: what it does in the engine, its file, and any quirk the emulation reproduces.
    """

    default: Any
    kind: str
    domain: tuple
    doc: str

    def accepted(self) -> str:
        """The accepted values as a user reads them in an error."""
        if self.kind in ("int", "float"):
            lo, hi = self.domain
            return f"{'an integer' if self.kind == 'int' else 'a number'} in [{lo:g}, {hi:g}]"
        return "one of " + ", ".join(_show(v) for v in self.domain)


def _show(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    return repr(v) if isinstance(v, str) else f"{v:g}" if isinstance(v, (int, float)) else str(v)


def validate_settings(engine: str, knobs: dict[str, Knob], settings: dict | None) -> dict:
    """`settings` checked against `knobs` and completed with their defaults: a ValueError naming the field
    (`settings.<knob>`) and listing what is accepted for an unknown knob, a wrong type or a value out of range
    (the caller maps it to HTTP 422 / exit 2). Ints stay ints, floats become floats."""
    settings = dict(settings or {})
    unknown = sorted(set(settings) - set(knobs))
    if unknown:
        raise ValueError(f"settings.{unknown[0]}: not a knob of {engine} (accepted: {', '.join(knobs)})")
    out = {}
    for name, knob in knobs.items():
        v = settings.get(name, knob.default)
        field = f"settings.{name}"
        if knob.kind == "bool":
            if not isinstance(v, bool) or v not in knob.domain:
                raise ValueError(f"{field}: expected {knob.accepted()}, got {v!r}")
        elif knob.kind == "choice":
            if isinstance(v, bool) or v not in knob.domain:
                raise ValueError(f"{field}: expected {knob.accepted()}, got {v!r}")
        else:
            ok_type = isinstance(v, int) if knob.kind == "int" else isinstance(v, (int, float))
            if isinstance(v, bool) or not ok_type or not math.isfinite(float(v)):
                raise ValueError(f"{field}: expected {knob.accepted()}, got {v!r}")
            lo, hi = knob.domain
            if not lo <= v <= hi:
                raise ValueError(f"{field}: expected {knob.accepted()}, got {v!r}")
            v = int(v) if knob.kind == "int" else float(v)
        out[name] = v
    return out
