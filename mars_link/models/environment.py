"""The air a flight meets: steady wind, 1-cosine gusts and Dryden turbulence, as scenario data.

Plain data and the published formulas only; sitl.environment applies it to JSBSim's own atmosphere
(FGWinds: `atmosphere/wind-*-fps`, `atmosphere/cosine-gust/*`, MIL-F-8785C turbulence).

Turbulence severities follow MIL-F-8785C (§3.7, Figs. 7, 10, 11) as JSBSim implements them: near the
ground (below 1000 ft) the intensity is set by the wind speed at 20 ft, W20 = 15 / 30 / 45 knots for
light / moderate / severe; above 2000 ft by the probability-of-exceedance curve, index 3 / 4 / 6
(1e-2 / 1e-3 / 1e-5). A number instead of a name is W20 in m/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

KNOT_MPS = 0.514444
FT_M = 0.3048
#: name -> (W20 in m/s, MIL-F-8785C probability-of-exceedance index)
SEVERITIES: dict[str, tuple[float, int]] = {
    "none": (0.0, 0),
    "light": (15 * KNOT_MPS, 3),
    "moderate": (30 * KNOT_MPS, 4),
    "severe": (45 * KNOT_MPS, 6),
}
TURBULENCE_MODELS = {"milspec": 3, "tustin": 4}  # JSBSim atmosphere/turb-type (FGWinds::tType)


@dataclass(frozen=True)
class Gust:
    """A 1-cosine gust in NED: rises over duration_s/2, holds hold_s, falls over duration_s/2."""

    t_s: float
    duration_s: float
    ned_mps: tuple[float, float, float]
    hold_s: float = 0.0

    @property
    def end_s(self) -> float:
        return self.t_s + self.duration_s + self.hold_s


@dataclass(frozen=True)
class EnvironmentParams:
    wind_ned_mps: tuple[float, float, float] = (0.0, 0.0, 0.0)
    turbulence_w20_mps: float = 0.0  # wind speed at 20 ft that sets the low-altitude intensity
    turbulence_severity: int = 0  # MIL-F-8785C probability-of-exceedance index (0 = off)
    turbulence_model: str = "milspec"
    gusts: tuple[Gust, ...] = ()

    @property
    def moves_air(self) -> bool:
        return any(self.wind_ned_mps) or self.turbulence_severity > 0 or bool(self.gusts)


def severity_of(value: str | float) -> tuple[float, int]:
    """(W20 m/s, exceedance index) of a severity name or a W20 number (index by the nearest named level)."""
    if isinstance(value, str):
        return SEVERITIES[value]
    w20 = float(value)
    if w20 == 0:
        return 0.0, 0
    index = 3 if w20 <= SEVERITIES["light"][0] else 4 if w20 <= SEVERITIES["moderate"][0] else 6
    return w20, index


def dryden_low_altitude(w20_mps: float, height_m: float) -> tuple[tuple[float, float, float], tuple[float, float]]:
    """MIL-F-8785C low-altitude Dryden figures: ((sigma_u, sigma_v, sigma_w) m/s, (L_u = L_v, L_w) m).

    h in feet clipped at 10 ft (as JSBSim): sigma_w = 0.1 W20, sigma_u = sigma_v = sigma_w / (0.177 +
    0.000823 h)^0.4, L_w = h, L_u = h / (0.177 + 0.000823 h)^1.2. Valid below 1000 ft.
    """
    h_ft = max(height_m / FT_M, 10.0)
    k = 0.177 + 0.000823 * h_ft
    sig_w = 0.1 * w20_mps
    sig_u = sig_w / k**0.4
    return (sig_u, sig_u, sig_w), (h_ft / k**1.2 * FT_M, h_ft * FT_M)


def check_vector(value, what: str) -> tuple[float, float, float]:
    """A finite [n, e, d] list, or ValueError naming what is wrong."""
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        got = f"{len(value)} values" if isinstance(value, (list, tuple)) else repr(value)
        raise ValueError(f"{what} must be [north, east, down] in m/s (3 numbers), got {got}")
    out = []
    for x in value:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x):
            raise ValueError(f"{what} must hold finite numbers, got {x!r}")
        out.append(float(x))
    return out[0], out[1], out[2]


def environment_doc(env: EnvironmentParams) -> dict:
    """The scenario's [environment] table for `env` (what mars_link.config.scenario_environment reads back)."""
    return {
        "wind_ned_mps": list(env.wind_ned_mps),
        "turbulence": env.turbulence_w20_mps,
        "turbulence_model": env.turbulence_model,
        "gusts": [{"t": g.t_s, "duration_s": g.duration_s, "ned_mps": list(g.ned_mps), "hold_s": g.hold_s}
                  for g in env.gusts],
    }
