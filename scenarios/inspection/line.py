"""A simulated production line: twin units, each with its own random mounting misalignment and
its own sensor, for the station's studies (the 200-unit proof, the line summary, the kill test).

Unit i of a line with seed s is always the same unit: its misalignment and its sensor are drawn
from (s, i) alone, so a line that was killed and is run again with the same seed and store
inspects exactly the units it has no record of.

Misalignments: on every judged axis uniform within +-``spread`` x the limit (1.3 by default:
about three units in four inside on each axis, a third of the units inside on all four of the
paper's axes), 0 on the axes not judged.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from scenarios.defaults import LINE_SPREAD as DEFAULT_SPREAD
from scenarios.inspection.verdict import EDGE_SCALE, edge_key, limits_si
from scenarios.station import Station


@dataclass(frozen=True)
class TwinUnit:
    """One unit of a simulated line: its name, misalignment (edge units) and sensor seed."""

    name: str
    misalignment: dict[str, float]
    seed: int


def line_units(station: Station, n: int, seed: int = 0, spread: float = DEFAULT_SPREAD,
               prefix: str | None = None) -> list[TwinUnit]:
    """The first n units of the line with this seed."""
    limits = limits_si(station.tolerances)
    prefix = f"sim{seed}-" if prefix is None else prefix
    out = []
    for i in range(n):
        rng = np.random.default_rng((int(seed), i, 1606))
        mis = {edge_key(a): float(rng.uniform(-spread, spread) * lim * EDGE_SCALE[a])
               for a, lim in limits.items()}
        # The sensor's seed: a different one for every unit and line.
        out.append(TwinUnit(f"{prefix}{i + 1:04d}", mis,
                            int(rng.integers(0, 2**31 - 1))))
    return out
