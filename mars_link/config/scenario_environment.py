"""Scenario tables for the air and the sensors: `[environment]` (wind, turbulence, gusts), `[vehicle]`'s
drag keys and `[sensors]` (the position sensor profile).

Each problem is one `UserInputError` line naming the file and the key (exit 2 at the CLI).
"""

from __future__ import annotations

from typing import Any

from mars_link.models.aerodynamics import AERO_PRESETS
from mars_link.models.environment import SEVERITIES, TURBULENCE_MODELS, EnvironmentParams, Gust, check_vector, severity_of
from mars_link.core.errors import UserInputError
from mars_link.models.sensor_profiles import GPS_FIGURES, PROFILES, SensorProfile
from mars_link.core.table_checks import number as _num

_ENV_KEYS = {"wind_ned_mps", "turbulence", "turbulence_model", "gusts"}
_GUST_KEYS = {"t", "duration_s", "ned_mps", "hold_s"}
MAX_TURBULENCE_W20_MPS = 100.0  # a hurricane at 20 ft; beyond it is not an intensity JSBSim was built for


def _vector(value: Any, what: str, src: str) -> tuple[float, float, float]:
    try:
        return check_vector(value, what)
    except ValueError as exc:
        raise UserInputError(f"{src}: {exc}") from None


def environment_table(table: dict, src: str) -> EnvironmentParams:
    """[environment]: wind_ned_mps = [n, e, d]; turbulence = "none" | "light" | "moderate" | "severe" or
    W20 in m/s; turbulence_model = "milspec" | "tustin"; [[environment.gusts]] t, duration_s, ned_mps, hold_s."""
    for key in table:
        if key not in _ENV_KEYS:
            raise UserInputError(f"{src}: unknown key {key!r} in [environment] (allowed: {', '.join(sorted(_ENV_KEYS))})")
    wind = _vector(table.get("wind_ned_mps", [0.0, 0.0, 0.0]), "[environment] wind_ned_mps", src)
    turb = table.get("turbulence", "none")
    if isinstance(turb, str):
        if turb not in SEVERITIES:
            raise UserInputError(f"{src}: unknown [environment] turbulence {turb!r} "
                                 f"(known: {', '.join(SEVERITIES)}, or W20 in m/s)")
    else:
        turb = _num(turb, "[environment] turbulence (W20, m/s)", src, nonneg=True)
        if turb > MAX_TURBULENCE_W20_MPS:
            raise UserInputError(f"{src}: [environment] turbulence must be <= {MAX_TURBULENCE_W20_MPS:g} m/s, got {turb:g}")
    w20, index = severity_of(turb)
    model = table.get("turbulence_model", "milspec")
    if model not in TURBULENCE_MODELS:
        raise UserInputError(f"{src}: unknown [environment] turbulence_model {model!r} "
                             f"(known: {', '.join(TURBULENCE_MODELS)})")
    gusts_doc = table.get("gusts", [])
    if not isinstance(gusts_doc, list):
        raise UserInputError(f"{src}: [environment] gusts must be an array of tables ([[environment.gusts]])")
    gusts = []
    for i, g in enumerate(gusts_doc, 1):
        where = f"[[environment.gusts]] #{i}"
        if not isinstance(g, dict):
            raise UserInputError(f"{src}: {where} must be a table")
        for key in g:
            if key not in _GUST_KEYS:
                raise UserInputError(f"{src}: unknown key {key!r} in {where} (allowed: {', '.join(sorted(_GUST_KEYS))})")
        for key in ("t", "duration_s", "ned_mps"):
            if key not in g:
                raise UserInputError(f"{src}: {where} needs {key!r}")
        gust = Gust(_num(g["t"], f"{where} t", src, nonneg=True),
                    _num(g["duration_s"], f"{where} duration_s", src, positive=True),
                    _vector(g["ned_mps"], f"{where} ned_mps", src),
                    _num(g.get("hold_s", 0.0), f"{where} hold_s", src, nonneg=True))
        if not any(gust.ned_mps):
            raise UserInputError(f"{src}: {where} ned_mps is zero (a gust needs a direction)")
        gusts.append(gust)
    gusts.sort(key=lambda g: g.t_s)
    for a, b in zip(gusts, gusts[1:]):
        if b.t_s < a.end_s:
            raise UserInputError(f"{src}: [[environment.gusts]] at t={a.t_s:g}s and t={b.t_s:g}s overlap "
                                 "(JSBSim runs one 1-cosine gust at a time)")
    return EnvironmentParams(wind, w20, index, model, tuple(gusts))


def aero_options(vehicle: dict, preset: str, environment: EnvironmentParams, src: str) -> dict:
    """VehicleParams fields for the air from [vehicle]: `drag` (default: on when the scenario moves the
    air) takes the preset's documented coefficients (mars_link.models.aerodynamics); `drag_area_frd_m2` and
    `rotor_drag_coeff` override them (the latter is read with the other numeric [vehicle] keys)."""
    drag = vehicle.get("drag", environment.moves_air)
    if not isinstance(drag, bool):
        raise UserInputError(f"{src}: [vehicle] drag must be true or false")
    explicit = "drag_area_frd_m2" in vehicle or "rotor_drag_coeff" in vehicle
    if environment.moves_air and not drag and not explicit:
        raise UserInputError(f"{src}: [environment] moves the air but [vehicle] drag = false: "
                             "the air would not act on the assembly")
    out: dict = dict(AERO_PRESETS[preset]) if drag else {}
    if "drag_area_frd_m2" in vehicle:
        area = vehicle["drag_area_frd_m2"]
        if not isinstance(area, list) or len(area) != 3:
            raise UserInputError(f"{src}: [vehicle] drag_area_frd_m2 must be [x, y, z] in m² (3 numbers)")
        out["drag_area_frd_m2"] = tuple(_num(a, "[vehicle] drag_area_frd_m2", src, nonneg=True) for a in area)
    return out


def sensors_table(table: dict, src: str) -> SensorProfile:
    """[sensors]: profile = "mocap" | "rtk" | "gps", and any of its figures overridden (position_rate_hz
    > 0, every other figure >= 0 but the declination; gps_walk_share <= 1; the gps-only figures only with profile "gps")."""
    name = table.get("profile", "mocap")
    if name not in PROFILES:
        raise UserInputError(f"{src}: unknown [sensors] profile {name!r} (known: {', '.join(PROFILES)})")
    profile = PROFILES[name]
    allowed = {"profile", *(k for k in profile.figures if profile.outdoor or k not in GPS_FIGURES)}
    for key in table:
        if key not in allowed:
            raise UserInputError(f"{src}: unknown key {key!r} in [sensors] for profile {name!r} "
                                 f"(allowed: {', '.join(sorted(allowed))})")
    figures = {key: _num(table[key], f"[sensors] {key}", src, positive=key == "position_rate_hz",
                       nonneg=key != "mag_declination_deg") for key in profile.figures if key in table}
    if figures.get("gps_walk_share", 0.0) > 1.0:
        raise UserInputError(f"{src}: [sensors] gps_walk_share must be <= 1 (a share of the variance), "
                             f"got {figures['gps_walk_share']:g}")
    if abs(figures.get("mag_declination_deg", 0.0)) > 180.0:
        raise UserInputError(f"{src}: [sensors] mag_declination_deg must be within +-180, got {figures['mag_declination_deg']:g}")
    return profile.with_overrides(**figures)
