"""The air's coefficients per vehicle preset: body drag (Cd·A) and rotor H-force drag.

Why here: the papers' plants (CoppeliaSim, paper 000; the ModQuad rig, paper 001) fly in still air with
no aerodynamics, so the presets keep 0 and a scenario turns the air on (`[vehicle] drag`, on by default
when it has an `[environment]`). The JSBSim model then computes both forces against the air
(sitl.jsbsim_model), wind, gusts and turbulence included.

The model is RotorPy's (Folk et al., "RotorPy: A Python-based Multirotor Simulator with Aerodynamics
for Education and Research", 2023; `rotorpy/vehicles/multirotor.py`, `compute_body_wrench`):

* parasitic body drag at the CoM, D = -|v_a| diag(c_Dx, c_Dy, c_Dz) v_a with v_a the body-frame
  airspeed; RotorPy's c_D (N/(m/s)²) is ½·ρ·Cd·A, so Cd·A = 2·c_D/ρ0 (ρ0 = 1.225 kg/m³, ISA sea level).
  JSBSim evaluates ½·ρ·Cd·A·|v_a|·v_a with its own density;
* rotor drag (H-force) per rotor at its hub, H = -ω·k_d·v_inplane, with v_inplane the rotor-plane
  part of the rotor's local airspeed (v_a + ω_body × r). The rotor speed follows the thrust,
  ω = sqrt(T/k_η), so H = -(k_d/sqrt(k_η))·sqrt(T)·v_inplane: linear in the in-plane airspeed and
  growing with the thrust (sqrt(T), as RotorPy; about the hover point this is the thrust-proportional
  linear drag of the rotor-drag literature). RotorPy's axial inflow term (k_z) and flapping moment
  (k_flap = 0 in its parameter files) are not modelled.

An assembly sums its units' Cd·A (no shielding between docked units: conservative for a rear row).
"""

from __future__ import annotations

import math

RHO_SEA_LEVEL_KGPM3 = 1.225


def drag_area_from_rotorpy(c_d_n_per_mps2: float) -> float:
    """Cd·A (m²) from RotorPy's parasitic drag coefficient c_D = ½·ρ·Cd·A (N/(m/s)²)."""
    return 2.0 * c_d_n_per_mps2 / RHO_SEA_LEVEL_KGPM3


def rotor_drag_from_rotorpy(k_d: float, k_eta: float) -> float:
    """H-force coefficient per sqrt(newton of thrust), N/(m/s)/sqrt(N): k_d / sqrt(k_eta)."""
    return k_d / math.sqrt(k_eta)


#: preset -> {VehicleParams field: value} applied when a scenario turns the air on
AERO_PRESETS: dict[str, dict] = {
    # 0.52 kg unit, 0.13 m arms: RotorPy's AscTec Hummingbird (0.5 kg, 0.17 m arms,
    # rotorpy/vehicles/hummingbird_params.py): c_D = (0.5e-2, 0.5e-2, 1e-2) N/(m/s)²,
    # k_d = 1.19e-4 kg/rad, k_eta = 5.57e-6 N/(rad/s)²  ->  Cd·A = (0.0082, 0.0082, 0.0163) m², c = 0.0504
    "mars-ftcc": {
        "drag_area_frd_m2": tuple(drag_area_from_rotorpy(c) for c in (0.5e-2, 0.5e-2, 1e-2)),
        "rotor_drag_coeff": rotor_drag_from_rotorpy(1.19e-4, 5.57e-6),
    },
    "mars-real": {  # the same airframe
        "drag_area_frd_m2": tuple(drag_area_from_rotorpy(c) for c in (0.5e-2, 0.5e-2, 1e-2)),
        "rotor_drag_coeff": rotor_drag_from_rotorpy(1.19e-4, 5.57e-6),
    },
    # Crazyflie 2.0: RotorPy's rotorpy/vehicles/crazyflie_params.py (k_d = 10.2506e-7 kg/rad,
    # k_eta = 2.3e-8 N/(rad/s)², from Förster 2015 "System identification of the Crazyflie 2.0");
    # that file sets the body's c_D to 0, and so do we (the cage's drag is not measured there).
    "modquad-cf2": {
        "drag_area_frd_m2": (0.0, 0.0, 0.0),
        "rotor_drag_coeff": rotor_drag_from_rotorpy(10.2506e-7, 2.3e-8),
    },
}
