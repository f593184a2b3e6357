"""The scenario's air applied to JSBSim's own atmosphere (FGWinds), body by body.

Why JSBSim's models and not a filter of ours: FGWinds already has the steady wind, the 1-cosine gust
and MIL-F-8785C Dryden turbulence (Milspec and Tustin discretisations), and the generated aircraft's
drag (sitl.jsbsim_model.aerodynamics_xml) is computed against its total wind. Property names from
JSBSim `src/models/atmosphere/FGWinds.cpp` (`FGWinds::bind`); turb-type 3 = Milspec, 4 = Tustin;
cosine-gust frame 3 = local NED.

Each body draws its turbulence from its own generator (`atmosphere/randomseed`), seeded from the world
seed and the order in which bodies appear, so a flight is the same in-process and in SITL. A gust
starts on the first exchange at or after its time, in every body that exists then.
"""

from __future__ import annotations

from mars_link.models.environment import TURBULENCE_MODELS, EnvironmentParams, Gust

FT = 0.3048
GUST_FRAME_LOCAL = 3
#: per-body seeds: world seed * this + body ordinal (keeps seeds of neighbouring worlds apart)
SEED_STRIDE = 1009


class Air:
    """Wind, turbulence and gust schedule for the bodies of one world."""

    def __init__(self, params: EnvironmentParams | None, seed: int) -> None:
        self.params = params or EnvironmentParams()
        self.seed = int(seed)
        self._attached: list = []  # the JsbsimBody objects set up (kept alive: no id reuse)
        self._pending: list[Gust] = sorted(self.params.gusts, key=lambda g: g.t_s)

    @property
    def active(self) -> bool:
        return self.params.moves_air

    def attach(self, bodies) -> None:
        """Set the steady wind and turbulence on every JsbsimBody not seen before (new bodies after docking)."""
        if not self.active:
            return
        p = self.params
        for body in bodies:
            if any(body is b for b in self._attached):
                continue
            fdm = body.fdm
            for axis, v in zip(("north", "east", "down"), p.wind_ned_mps):
                fdm[f"atmosphere/wind-{axis}-fps"] = v / FT
            if p.turbulence_severity > 0:
                fdm["atmosphere/randomseed"] = (self.seed * SEED_STRIDE + len(self._attached)) % (2**31 - 1)
                fdm["atmosphere/turb-type"] = TURBULENCE_MODELS[p.turbulence_model]
                fdm["atmosphere/turbulence/milspec/windspeed_at_20ft_AGL-fps"] = p.turbulence_w20_mps / FT
                fdm["atmosphere/turbulence/milspec/severity"] = p.turbulence_severity
            self._attached.append(body)

    def before_exchange(self, t_s: float, bodies) -> None:
        """Start the gusts due by `t_s` (the time at the start of the coming exchange period)."""
        while self._pending and self._pending[0].t_s <= t_s + 1e-9:
            gust = self._pending.pop(0)
            for body in bodies:
                start_gust(body.fdm, gust)


def start_gust(fdm, gust: Gust) -> None:
    """JSBSim's 1-cosine gust: (1 - cos) rise over duration/2, hold, (1 - cos) fall over duration/2."""
    n, e, d = gust.ned_mps
    magnitude = (n * n + e * e + d * d) ** 0.5
    fdm["atmosphere/cosine-gust/startup-duration-sec"] = gust.duration_s / 2
    fdm["atmosphere/cosine-gust/steady-duration-sec"] = gust.hold_s
    fdm["atmosphere/cosine-gust/end-duration-sec"] = gust.duration_s / 2
    fdm["atmosphere/cosine-gust/magnitude-ft_sec"] = magnitude / FT
    fdm["atmosphere/cosine-gust/frame"] = GUST_FRAME_LOCAL
    fdm["atmosphere/cosine-gust/X-velocity-ft_sec"] = n / magnitude
    fdm["atmosphere/cosine-gust/Y-velocity-ft_sec"] = e / magnitude
    fdm["atmosphere/cosine-gust/Z-velocity-ft_sec"] = d / magnitude
    fdm["atmosphere/cosine-gust/start"] = 1
