"""Haas NGC interpreter: the Fanuc one reading skip positions by letter."""

from __future__ import annotations

from simulators.gcode.fanuc import FanucInterpreter


class HaasInterpreter(FanucInterpreter):
    """Haas NGC: Fanuc macro syntax; skip positions by letter (#5064 A, #5065 B, #5066 C)."""

    def store_probe(self, latched: dict[str, float], triggered: bool) -> None:
        for a, v in latched.items():
            self.variables[f"#{5061 + 'XYZABC'.index(a)}"] = v

    def lookup(self, name: str) -> float | str:
        if name.startswith("#") and name[1:].isdigit():
            n = int(name[1:])
            for base in (5001, 5021, 5041):
                if base <= n < base + 6:
                    return self.io.position().get("XYZABC"[n - base], 0.0)
        return super().lookup(name)
