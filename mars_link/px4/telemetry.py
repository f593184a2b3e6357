"""The unit's `/fmu/out` telemetry built from SI quantities (world NED, body FRD, as PX4 and this project
use them): what the integrator hands over from the unit's sensors and estimate, without I/O.

Time stamps are integer microseconds of the simulated clock (`time_s` since the unit's boot), as PX4's
hrt time. Fields a simulated unit has no value for are left as PX4 leaves them (NaN for unknown
variances and limits, zero counters)."""

from __future__ import annotations

import math

import numpy as np

from mars_link.px4.cdr import BatteryStatus, SensorCombined, VehicleLocalPosition, VehicleOdometry
from mars_link.px4.unit_interface import time_us


def _vec(values, n: int) -> np.ndarray:
    arr = np.asarray(values, dtype=np.float32).reshape(-1)
    if arr.shape != (n,):
        raise ValueError(f"expected {n} values, got {arr.shape}")
    return arr


def vehicle_odometry(time_s: float, position_ned_m, quaternion_wxyz, velocity_ned_mps,
                     angular_velocity_frd_radps, *, sample_time_s: float | None = None) -> VehicleOdometry:
    """Pose in NED, velocity in NED, body rates in FRD."""
    nan3 = np.full(3, np.nan, dtype=np.float32)
    return VehicleOdometry(
        timestamp=time_us(time_s), timestamp_sample=time_us(time_s if sample_time_s is None else sample_time_s),
        pose_frame=VehicleOdometry.POSE_FRAME_NED, position=_vec(position_ned_m, 3), q=_vec(quaternion_wxyz, 4),
        velocity_frame=VehicleOdometry.VELOCITY_FRAME_NED, velocity=_vec(velocity_ned_mps, 3),
        angular_velocity=_vec(angular_velocity_frd_radps, 3),
        position_variance=nan3.copy(), orientation_variance=nan3.copy(), velocity_variance=nan3.copy(),
        reset_counter=0, quality=0)


def sensor_combined(time_s: float, gyro_frd_radps, accel_frd_mps2, *, integral_dt_s: float) -> SensorCombined:
    """One IMU sample (the accelerometer read at the gyro's time); `integral_dt_s` the sampling period."""
    dt_us = time_us(integral_dt_s)
    return SensorCombined(timestamp=time_us(time_s), gyro_rad=_vec(gyro_frd_radps, 3), gyro_integral_dt=dt_us,
                          accelerometer_timestamp_relative=0, accelerometer_m_s2=_vec(accel_frd_mps2, 3),
                          accelerometer_integral_dt=dt_us)


def vehicle_local_position(time_s: float, position_ned_m, velocity_ned_mps, acceleration_ned_mps2,
                           heading_rad: float, *, ref_lat_deg: float = math.nan, ref_lon_deg: float = math.nan,
                           ref_alt_m: float = math.nan) -> VehicleLocalPosition:
    p = _vec(position_ned_m, 3)
    v = _vec(velocity_ned_mps, 3)
    a = _vec(acceleration_ned_mps2, 3)
    has_ref = math.isfinite(ref_lat_deg) and math.isfinite(ref_lon_deg)
    inf = float("inf")
    return VehicleLocalPosition(
        timestamp=time_us(time_s), timestamp_sample=time_us(time_s),
        xy_valid=True, z_valid=True, v_xy_valid=True, v_z_valid=True,
        x=float(p[0]), y=float(p[1]), z=float(p[2]), vx=float(v[0]), vy=float(v[1]), vz=float(v[2]),
        z_deriv=float(v[2]), ax=float(a[0]), ay=float(a[1]), az=float(a[2]),
        heading=float(heading_rad), heading_var=math.nan, unaided_heading=math.nan, heading_good_for_control=True,
        tilt_var=math.nan, xy_global=has_ref, z_global=math.isfinite(ref_alt_m),
        ref_timestamp=time_us(time_s) if has_ref else 0,
        ref_lat=ref_lat_deg, ref_lon=ref_lon_deg, ref_alt=ref_alt_m,
        dist_bottom=math.nan, dist_bottom_var=math.nan,
        eph=math.nan, epv=math.nan, evh=math.nan, evv=math.nan,
        vxy_max=inf, vz_max=inf, hagl_min=inf, hagl_max_z=inf, hagl_max_xy=inf)


def battery_status(time_s: float, voltage_v: float, current_a: float, remaining_fraction: float, *,
                   discharged_mah: float = math.nan, cell_count: int = 0, battery_id: int = 1,
                   warning: int = BatteryStatus.WARNING_NONE) -> BatteryStatus:
    cells = np.full(14, np.nan, dtype=np.float32)
    if cell_count:
        cells[:cell_count] = voltage_v / cell_count
    return BatteryStatus(
        timestamp=time_us(time_s), connected=True, voltage_v=voltage_v, current_a=current_a,
        current_average_a=current_a, discharged_mah=discharged_mah, remaining=remaining_fraction, scale=1.0,
        time_remaining_s=math.nan, temperature=math.nan, cell_count=cell_count,
        source=BatteryStatus.SOURCE_POWER_MODULE, id=battery_id, voltage_cell_v=cells,
        max_cell_voltage_delta=0.0, warning=warning, full_charge_capacity_wh=math.nan,
        remaining_capacity_wh=math.nan, nominal_voltage=math.nan, internal_resistance_estimate=math.nan,
        ocv_estimate=math.nan, ocv_estimate_filtered=math.nan, volt_based_soc_estimate=math.nan,
        voltage_prediction=math.nan, prediction_error=math.nan, estimation_covariance_norm=math.nan)
