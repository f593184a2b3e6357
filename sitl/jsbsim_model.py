"""Generate a JSBSim aircraft definition for an assembly (specs/dependencies.md §1.2).

One pointmass per unit (JSBSim sums the parallel-axis terms itself), a non-rotating spherical planet
with g = 9.80665 m/s² at the surface, ground contacts on the hull of the units' feet, and the rotors' net thrust and moments as one BODY
force and three BODY moments in `external_reactions` (the per-rotor sums are made in sitl.physics). When the vehicle feels the
air (mars_link.models.aerodynamics), the `aerodynamics` section holds body drag and rotor H-force drag as
body-axis functions of JSBSim's own airspeed (wind, gusts and turbulence included).

JSBSim's structural frame is x aft, y right, z up; body FRD positions convert as x_s = -x, y_s = y,
z_s = -z. That conversion happens here and nowhere else.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial import ConvexHull

from mars_link.core.assembly import GRAVITY_MPS2, AssemblyModel

FT_M = 0.3048
LBF_N = 4.4482216152605

EARTH_RADIUS_M = 6371000.0
SLUGFT2_PER_KGM2 = 14.593902937206364 * 0.3048**2  # kg·m² in one slug·ft²
#: tiny structural mass so JSBSim has an empty weight; compensated in `JsbsimBody` mass checks
EMPTY_MASS_KG = 1e-6
CONTACT_SPRING_N_PER_M_PER_KG = 20000.0  # total stiffness per kg of assembly: g / 20000 = 0.49 mm at rest
CONTACT_DAMPING_RATIO = 1.2  # of the vertical mode: overdamped, a landed body sinks without bounce


def _structural(p_frd) -> tuple[float, float, float]:
    return (-float(p_frd[0]), float(p_frd[1]), -float(p_frd[2]))


def unit_feet_frd_m(model: AssemblyModel) -> np.ndarray:
    """All landing feet (4 per unit, under the rotor arms, `gear_depth_m` below the unit centre)."""
    v = model.vehicle
    a = v.rotor_offset_m
    feet = []
    for uid in model.unit_ids:
        c = model.unit_position(uid)
        for sx, sy in ((1, 1), (1, -1), (-1, -1), (-1, 1)):
            feet.append((c[0] + sx * a, c[1] + sy * a, c[2] + v.gear_depth_m))
    return np.array(feet)


def contact_points(model: AssemblyModel) -> list[tuple[np.ndarray, float]]:
    """Ground contacts as (position FRD m, share of the total stiffness), on the feet's convex hull.

    Each JSBSim contact costs ~0.8 us per step (24 feet of a 3x2 assembly = 80 % of the step). All feet
    lie in one plane, so on flat ground only the hull corners can ever touch first. An inner foot's
    stiffness is split over the corners of a hull triangle containing it by its barycentric
    coordinates: total stiffness and its first moment (the centroid of all feet = the CoM) are kept,
    so a resting assembly sinks level, as it would on all its feet.
    """
    feet = unit_feet_frd_m(model)
    xy = feet[:, :2]
    hull = list(ConvexHull(xy).vertices)  # counter-clockwise in (x, y)
    n = len(hull)
    # averaged over the fans from every corner, so symmetric layouts get symmetric shares
    share = sum(np.roll(_barycentric_in_fan(np.roll(xy[hull], -r, axis=0), xy), r, axis=1) for r in range(n)) / n
    share = share.sum(axis=0) / len(feet)
    return [(feet[i], float(share[k])) for k, i in enumerate(hull)]


def _barycentric_in_fan(poly: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Weights (>= 0, each row summing to 1) of the polygon corners that reproduce each point, from the
    fan triangle that holds it (all points solved at once per triangle: a 20x20 has 1,600 feet)."""
    rows = np.arange(len(points))
    rhs = np.vstack([points.T, np.ones(len(points))])
    best = np.full(len(points), -np.inf)
    best_w = np.zeros((len(points), 3))
    best_j = np.zeros(len(points), dtype=int)
    for j in range(1, len(poly) - 1):
        tri = poly[[0, j, j + 1]]
        w = np.linalg.solve(np.vstack([tri.T, np.ones(3)]), rhs).T
        low = w.min(axis=1)
        better = low > best  # the triangle that holds a point best (all weights >= 0 up to rounding)
        best[better], best_w[better], best_j[better] = low[better], w[better], j
    w = np.clip(best_w, 0.0, None)
    w /= w.sum(axis=1, keepdims=True)
    weights = np.zeros((len(points), len(poly)))
    weights[rows, 0] += w[:, 0]
    weights[rows, best_j] += w[:, 1]
    weights[rows, best_j + 1] += w[:, 2]
    return weights


#: the rotors' net effect, written by sitl.physics each step: total thrust (lbf, along body -z, at the model
#: origin) and the body roll, pitch and yaw moments about that origin (lbf·ft). Four writes and four
#: reactions whatever the rotor count: one force and one moment per rotor made JSBSim's step and the
#: writes grow with the assembly (10x10: 800 reactions, about a third of the loop's physics time).
ROTOR_FORCE = "rotors"
ROTOR_MOMENTS = ("rotors_l", "rotors_m", "rotors_n")


def aircraft_xml(model: AssemblyModel, name: str) -> str:
    v = model.vehicle
    ju = v.unit_inertia_kgm2
    mass = model.mass_kg
    # stiffness scaled with mass so the static compression (g / 20000 ~ 0.5 mm) is the same for any size
    k_total = CONTACT_SPRING_N_PER_M_PER_KG * mass
    c_total = 2.0 * CONTACT_DAMPING_RATIO * (k_total * mass) ** 0.5
    lines = [
        '<?xml version="1.0"?>',
        f'<fdm_config name="{name}" version="2.0" release="ALPHA">',
        "  <fileheader><author>mars-link</author><description>generated assembly</description></fileheader>",
        "  <planet>",
        f'    <equatorial_radius unit="M">{EARTH_RADIUS_M}</equatorial_radius>',
        f'    <polar_radius unit="M">{EARTH_RADIUS_M}</polar_radius>',
        '    <rotation_rate unit="RAD/SEC">0.0</rotation_rate>',
        f'    <GM unit="M3/SEC2">{GRAVITY_MPS2 * EARTH_RADIUS_M ** 2:.10e}</GM>',
        "    <J2>0.0</J2>",
        "  </planet>",
        "  <metrics>",
        '    <wingarea unit="M2">0.1</wingarea><wingspan unit="M">0.3</wingspan><chord unit="M">0.3</chord>',
        '    <htailarea unit="M2">0</htailarea><htailarm unit="M">0</htailarm>',
        '    <vtailarea unit="M2">0</vtailarea><vtailarm unit="M">0</vtailarm>',
        '    <location name="AERORP" unit="M"><x>0</x><y>0</y><z>0</z></location>',
        '    <location name="EYEPOINT" unit="M"><x>0</x><y>0</y><z>0</z></location>',
        '    <location name="VRP" unit="M"><x>0</x><y>0</y><z>0</z></location>',
        "  </metrics>",
        "  <mass_balance>",
        f'    <ixx unit="KG*M2">1e-9</ixx><iyy unit="KG*M2">1e-9</iyy><izz unit="KG*M2">1e-9</izz>',
        f'    <emptywt unit="KG">{EMPTY_MASS_KG}</emptywt>',
        '    <location name="CG" unit="M"><x>0</x><y>0</y><z>0</z></location>',
    ]
    for uid in model.unit_ids:
        x, y, z = _structural(model.unit_position(uid))
        lines += [
            f'    <pointmass name="unit{uid}">',
            f'      <weight unit="KG">{v.unit_mass_kg}</weight>',
            # slug·ft² written directly: JSBSim's own KG*M2 factor is off by ~9e-5
            f'      <ixx unit="SLUG*FT2">{ju[0] / SLUGFT2_PER_KGM2:.12e}</ixx>'
            f'<iyy unit="SLUG*FT2">{ju[1] / SLUGFT2_PER_KGM2:.12e}</iyy>'
            f'<izz unit="SLUG*FT2">{ju[2] / SLUGFT2_PER_KGM2:.12e}</izz>',
            f'      <location unit="M"><x>{x:.9f}</x><y>{y:.9f}</y><z>{z:.9f}</z></location>',
            "    </pointmass>",
        ]
    lines += ["  </mass_balance>", "  <ground_reactions>"]
    for i, (p, share) in enumerate(contact_points(model)):
        x, y, z = _structural(p)
        lines += [
            f'    <contact type="STRUCTURE" name="foot{i}">',
            f'      <location unit="M"><x>{x:.9f}</x><y>{y:.9f}</y><z>{z:.9f}</z></location>',
            "      <static_friction>0.8</static_friction><dynamic_friction>0.5</dynamic_friction>",
            f'      <spring_coeff unit="N/M">{k_total * share:.6f}</spring_coeff>',
            f'      <damping_coeff unit="N/M/SEC">{c_total * share:.6f}</damping_coeff>',
            "    </contact>",
        ]
    lines += ["  </ground_reactions>", "  <external_reactions>",
              # every rotor pushes along body -z: their sum acts at the model origin, and the moments of the
              # thrusts about that origin and their reaction torques are three BODY moments (sitl.physics)
              f'    <force name="{ROTOR_FORCE}" frame="BODY" unit="LBS">',
              '      <location unit="M"><x>0</x><y>0</y><z>0</z></location>',
              "      <direction><x>0</x><y>0</y><z>-1</z></direction>",
              "    </force>"]
    for name, axis in zip(ROTOR_MOMENTS, ("<x>1</x><y>0</y><z>0</z>", "<x>0</x><y>1</y><z>0</z>",
                                          "<x>0</x><y>0</y><z>1</z>")):
        lines += [f'    <moment name="{name}" frame="BODY" unit="LBSFT">',
                  f"      <direction>{axis}</direction>",
                  "    </moment>"]
    lines += ["  </external_reactions>", *aerodynamics_xml(model), "</fdm_config>", ""]
    return "\n".join(lines)


#: rotor sums the physics writes with the thrusts: sum sqrt(T) (sqrt N), its first moments about the
#: CoM along body x and y (sqrt N·m) and its second moment x² + y² (sqrt N·m²)
ROTOR_SUM_PROPERTIES = ("aero/mars/rotor-sqrt-thrust", "aero/mars/rotor-sqrt-thrust-x", "aero/mars/rotor-sqrt-thrust-y",
                        "aero/mars/rotor-sqrt-thrust-r2")


def _product(*terms: str) -> str:
    parts = "".join(f"<value>{t!r}</value>" if isinstance(t, float) else f"<property>{t}</property>" for t in terms)
    return f"<product>{parts}</product>"


def aerodynamics_xml(model: AssemblyModel) -> list[str]:
    """Body drag at the CoM and rotor H-force drag, in JSBSim's body axes (lbf, lbf·ft).

    Body drag per axis i: -½·ρ·(Cd·A)_i·|v_a|·v_a,i, Cd·A summed over the units. Rotor drag (the rotor
    plane is the body x-y plane, every rotor at z = 0): each rotor's in-plane airspeed is the CoM
    airspeed plus r × (its position), so with S = Σ sqrt(T_i), Sx = Σ sqrt(T_i)·x_i, Sy, Sr2 the forces
    are X = -c(S·u - r·Sy), Y = -c(S·v + r·Sx) and the yaw moment N = -c(Sx·v - Sy·u + r·Sr2). Empty
    when the vehicle has no drag (still-air plants stay exactly as before).
    """
    v = model.vehicle
    if not v.has_drag:
        return ["  <aerodynamics/>"]
    n = model.n_units
    rho, vt = "atmosphere/rho-slugs_ft3", "velocities/vt-fps"
    air = {"X": "velocities/u-aero-fps", "Y": "velocities/v-aero-fps", "Z": "velocities/w-aero-fps"}
    c = v.rotor_drag_coeff
    s, sx, sy, sr2 = ROTOR_SUM_PROPERTIES
    lines = ["  <aerodynamics>"]
    lines += [f'    <property value="0">{p}</property>' for p in ROTOR_SUM_PROPERTIES]
    for k, axis in enumerate(("X", "Y", "Z")):
        cda_ft2 = n * v.drag_area_frd_m2[k] / FT_M**2
        terms = [_product(-0.5 * cda_ft2, rho, vt, air[axis])]
        if c > 0 and axis == "X":
            terms += [_product(-c * FT_M / LBF_N, s, air["X"]), _product(c / LBF_N, "velocities/r-rad_sec", sy)]
        if c > 0 and axis == "Y":
            terms += [_product(-c * FT_M / LBF_N, s, air["Y"]), _product(-c / LBF_N, "velocities/r-rad_sec", sx)]
        lines += [f'    <axis name="{axis}" frame="BODY">',
                  f'      <function name="aero/mars/force-{axis.lower()}-lbs"><sum>{"".join(terms)}<value>0</value></sum></function>',
                  "    </axis>"]
    if c > 0:
        terms = [_product(-c / LBF_N, sx, air["Y"]), _product(c / LBF_N, sy, air["X"]),
                 _product(-c / (LBF_N * FT_M), "velocities/r-rad_sec", sr2)]
        lines += ['    <axis name="YAW" frame="BODY">',
                  f'      <function name="aero/mars/moment-yaw-lbsft"><sum>{"".join(terms)}</sum></function>',
                  "    </axis>"]
    lines.append("  </aerodynamics>")
    return lines


def write_aircraft(model: AssemblyModel, root_dir: Path, name: str) -> Path:
    """Write <root_dir>/aircraft/<name>/<name>.xml (the layout `FGFDMExec(root_dir).load_model(name)`
    expects) and return its path."""
    path = Path(root_dir) / "aircraft" / name / f"{name}.xml"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(aircraft_xml(model, name), encoding="utf-8")
    return path
