"""Parameters of interaction logs (``deploy.interaction``): pushes and a carried load at every FT sensor's
site (`pipeline.sim.sites`, `pipeline.sim.push`). Light imports only: the deployment params load it."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from pipeline.core.errors import ConfigError
from pipeline.sim.params import check_number, check_order, three_numbers


@dataclass(frozen=True)
class InteractionParams:
    """Pushes and a carried load at every FT sensor's site, the robot on the pole (``deploy.interaction``).

    The log of type ``interaction`` pushes each sensor's site (`pipeline.sim.sites`: hands, ankles, the
    front and rear of both soles) once per direction, a half-sine of `duration_s` every `period_s`, peak
    forces cycling through 4 levels evenly spaced in `force_n`; then each arm's site holds a mass of
    `load_kg` for `load_s`. The motion is unchanged (stiff position control), as for `PushParams`.
    """

    force_n: tuple[float, float]  # range of the pushes' peak forces, N
    duration_s: float  # length of a push, s
    period_s: float  # a push starts every this many seconds, s
    directions: tuple[tuple[float, float, float], ...]  # world (root_link) frame, normalised
    sites: dict[str, Any]  # sensor -> {link, point}: sites replacing the derived ones
    load_kg: float  # mass of the carried load, kg (0: none)
    load_s: float  # how long each arm's site holds it, s

    SECTION = "deploy.interaction"

    def __post_init__(self) -> None:
        f = self.force_n
        ok = isinstance(f, list | tuple) and len(f) == 2
        ok = ok and all(isinstance(v, int | float) and not isinstance(v, bool) for v in f)
        if not ok or not 0.0 < f[0] <= f[1] <= 2000.0:
            raise ConfigError(f"{self.SECTION}.force_n must be [min, max] N with 0 < min <= max, got {f!r}")
        object.__setattr__(self, "force_n", (float(f[0]), float(f[1])))
        check_number(self, "duration_s", 0.0, 60.0, lo_open=True)
        check_number(self, "period_s", 0.0, 600.0, lo_open=True)
        check_order(self, "duration_s", "period_s")
        check_number(self, "load_kg", 0.0, 100.0, hi_open=False)
        check_number(self, "load_s", 0.0, 600.0)
        dirs = self.directions
        if not isinstance(dirs, list | tuple) or not dirs:
            raise ConfigError(
                f"{self.SECTION}.directions must be a non-empty list of 3-vectors, got {dirs!r}"
            )
        unit = []
        for i, d in enumerate(dirs):
            v = three_numbers(d, f"{self.SECTION}.directions[{i}]")
            if math.hypot(*v) == 0.0:
                raise ConfigError(f"{self.SECTION}.directions[{i}] must not be zero")
            unit.append(tuple(c / math.hypot(*v) for c in v))
        object.__setattr__(self, "directions", tuple(unit))
        if not isinstance(self.sites, dict):
            raise ConfigError(f"{self.SECTION}.sites must be a mapping sensor -> {{link, point}}")
        for sensor, entry in self.sites.items():
            if not isinstance(entry, dict) or "link" not in entry or set(entry) - {"link", "point"}:
                raise ConfigError(f"{self.SECTION}.sites.{sensor} must be {{link, point}}, got {entry!r}")
            three_numbers(entry.get("point", (0, 0, 0)), f"{self.SECTION}.sites.{sensor}.point")
