"""Trajectory kinds: derivatives, the paper's spiral after the frame map, ground starts, bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mars_link.core.errors import UserInputError
from mars_link.models.trajectories import TRAJECTORY_KINDS, build_trajectory

REST = 0.05


def make(kind, tmp_path=None, **params):
    if kind == "waypoints" and "points" not in params:
        params["points"] = [[0.0, 0.0, -1.5], [2.0, 1.0, -2.0], [3.0, -1.0, -1.0]]
    if kind == "csv" and "path" not in params:
        path = tmp_path / "ref.csv"
        t = np.linspace(0, 10, 101)
        path.write_text("t,n,e,d,yaw\n" + "\n".join(f"{a},{math.sin(a)},{0.1*a},{-1.0},{0.01*a}" for a in t))
        params["path"] = str(path)
    return build_trajectory(kind, params, REST)


VARIANTS = [(k, {}) for k in TRAJECTORY_KINDS if k != "csv"] + [
    ("helix", {"centre_ne_m": [-0.6, 0.8], "period_s": 7.0, "height_m": 2.5, "turns": 1.5}),
    ("waypoints", {"points": [[1.0, 1.0, -1.0], [6.0, 1.0, -1.0], [6.0, 1.5, -1.2], [2.0, 3.0, -2.0]],
                   "cruise_mps": 1.2}),
    ("hover", {"yaw_deg": 45.0, "height_m": 3.0}),
]


@pytest.mark.parametrize("kind,params", VARIANTS)
def test_derivatives_agree_with_finite_differences(kind: str, params: dict) -> None:
    traj = make(kind, **params)
    h = 1e-4
    for t in np.linspace(0.3, traj.duration_s - 0.3, 37):
        a, b = traj.sample(t - h), traj.sample(t + h)
        mid = traj.sample(t)
        np.testing.assert_allclose((b.position_ned_m - a.position_ned_m) / (2 * h), mid.velocity_ned_mps, atol=2e-5)
        np.testing.assert_allclose((b.velocity_ned_mps - a.velocity_ned_mps) / (2 * h), mid.acceleration_ned_mps2, atol=2e-4)
        np.testing.assert_allclose((b.acceleration_ned_mps2 - a.acceleration_ned_mps2) / (2 * h), mid.jerk_ned_mps3, atol=2e-3)


@pytest.mark.parametrize("kind", TRAJECTORY_KINDS)
def test_every_kind_starts_on_the_ground_at_rest(kind: str, tmp_path) -> None:
    p = make(kind, tmp_path).sample(0.0)
    assert p.position_ned_m[2] == pytest.approx(-REST)
    if kind == "mars-ftcc-spiral":  # the paper's reference moves off at 0.5 m/s from t = 0 (ftc.md §7.1)
        assert np.linalg.norm(p.velocity_ned_mps[:2]) == pytest.approx(0.5, rel=0.01)
        return
    np.testing.assert_allclose(p.velocity_ned_mps, 0.0, atol=1e-12)
    np.testing.assert_allclose(p.acceleration_ned_mps2, 0.0, atol=1e-12)


def test_spiral_matches_the_papers_formula_after_the_frame_map() -> None:
    traj = build_trajectory("mars-ftcc-spiral", {}, REST, start_ned_m=(1.0, -2.0))
    k, T = 0.5, 40.0
    assert traj.duration_s == pytest.approx(4 * 2 * math.pi / k)
    for t in (0.0, 3.7, 12.5, 31.0, 50.0):
        a = 1 - k * t / T
        xs, ys, zs = a * math.cos(k * t) - 1, a * math.sin(k * t) + 0.35, 0.1 * k * t
        # scene start (0, 0.35, 0) is the tracked unit; NED: north = y_s, east = x_s, down = -z_s
        expected = np.array([1.0 + (ys - 0.35), -2.0 + (xs - 0.0), -zs - REST])
        np.testing.assert_allclose(traj.sample(t).position_ned_m, expected, atol=1e-12)


def test_min_snap_passes_through_its_waypoints_with_continuous_derivatives() -> None:
    pts = [[0.0, 0.0, -1.5], [2.0, 1.0, -2.0], [3.0, -1.0, -1.0]]
    traj = make("waypoints", points=pts)
    for knot, p in zip(traj.t_knots[1:], pts):
        np.testing.assert_allclose(traj.sample(knot).position_ned_m, p, atol=1e-9)
        a, b = traj.sample(knot - 1e-7), traj.sample(knot + 1e-7)
        np.testing.assert_allclose(a.acceleration_ned_mps2, b.acceleration_ned_mps2, atol=1e-4)
    for knot in traj.t_knots[2:-1]:  # interior min-snap points: C6, so jerk joins too
        a, b = traj.sample(knot - 1e-7), traj.sample(knot + 1e-7)
        assert np.linalg.norm(a.velocity_ned_mps) > 0.1  # flies through, does not stop
        np.testing.assert_allclose(a.velocity_ned_mps, b.velocity_ned_mps, atol=1e-5)
        np.testing.assert_allclose(a.jerk_ned_mps3, b.jerk_ned_mps3, atol=1e-3)
    end = traj.sample(traj.duration_s)
    np.testing.assert_allclose(end.position_ned_m, pts[-1], atol=1e-9)
    np.testing.assert_allclose(end.velocity_ned_mps, 0.0, atol=1e-9)


def test_min_snap_is_retimed_to_the_cruise_speed_and_stays_above_ground() -> None:
    pts = [[0.0, 0.0, -1.0], [20.0, 0.0, -1.0], [20.0, 1.0, -1.0], [0.0, 2.0, -0.5]]
    traj = make("waypoints", points=pts, cruise_mps=1.5)
    ts = np.linspace(0.0, traj.duration_s, 4000)
    samples = [traj.sample(t) for t in ts]
    speeds = np.array([np.linalg.norm(p.velocity_ned_mps) for p in samples])
    assert 1.4 < speeds.max() < 1.6  # peaks at the cruise speed, short hops slower
    assert max(p.position_ned_m[2] for p in samples) <= -REST + 1e-9
    # the take-off is straight up under the first point
    climb = np.array([p.position_ned_m for p, t in zip(samples, ts) if t <= traj.t_knots[1]])
    np.testing.assert_allclose(climb[:, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(traj.sample(traj.t_knots[1]).position_ned_m, pts[0], atol=1e-12)
    with pytest.raises(UserInputError, match="waypoint 2"):
        make("waypoints", points=[[0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])


def test_helix_geometry_centre_period_and_height() -> None:
    traj = make("helix", centre_ne_m=[0.0, -2.0], period_s=8.0, height_m=3.0, turns=2.0, start_height_m=1.0,
                ramp_s=2.0, climb_s=3.0, hold_s=1.0)
    centre = np.array([0.0, -2.0])
    for t in np.linspace(3.0, traj.duration_s, 50):
        p = traj.sample(t).position_ned_m
        assert np.hypot(*(p[:2] - centre)) == pytest.approx(2.0, abs=1e-9)
    end = traj.sample(traj.duration_s).position_ned_m
    np.testing.assert_allclose(end, [0.0, 0.0, -3.0 - REST], atol=1e-9)  # two whole turns, 3 m up
    # cruise angular rate is one turn per period_s
    mid = traj.sample(3.0 + 2.0 + 4.0)
    assert np.linalg.norm(mid.velocity_ned_mps[:2]) == pytest.approx(2.0 * 2 * math.pi / 8.0, rel=1e-9)
    assert traj.duration_s == pytest.approx(3.0 + 2 * 2.0 + (4 * math.pi - 2 * math.pi / 8.0 * 2.0) / (2 * math.pi / 8.0) + 1.0)


def test_csv_replays_after_a_takeoff(tmp_path) -> None:
    traj = make("csv", tmp_path)
    c = traj.climb_s
    assert c > 0
    p = traj.sample(c + 2.55)
    np.testing.assert_allclose(p.position_ned_m, [math.sin(2.5) + 0.5 * (math.sin(2.6) - math.sin(2.5)), 0.255, -1.0], atol=1e-9)
    assert p.yaw_rad == pytest.approx(0.0255)
    np.testing.assert_allclose(traj.sample(c + 99).position_ned_m, [math.sin(10.0), 1.0, -1.0])


@pytest.mark.parametrize(
    "kind,params,needle",
    [
        ("zigzag", {}, "unknown kind 'zigzag'"),
        ("hover", {"radius_m": 1.0}, "unknown key 'radius_m' for kind 'hover'"),
        ("helix", {"radius_m": -1.0}, "radius_m must be > 0"),
        ("helix", {"turns": "two"}, "turns must be a number"),
        ("waypoints", {}, "needs 'points'"),
        ("waypoints", {"points": [[1, 2]]}, "points must be a list of [n, e, d]"),
        ("csv", {"path": "no/such.csv"}, "cannot be read"),
        ("helix", {"radius_m": 1.0, "centre_ne_m": [0, 1]}, "radius_m or centre_ne_m"),
        ("helix", {"speed_mps": 1.0, "period_s": 5.0}, "speed_mps or period_s"),
        ("helix", {"centre_ne_m": [1]}, "centre_ne_m must be [n, e]"),
        ("helix", {"turns": 0.1}, "turns too few"),
        ("helix", {"hold_s": -1.0}, "hold_s must be >= 0"),
        ("hover", {"climb_s": 5.0, "duration_s": 2.0}, "duration_s must be >= climb_s"),
    ],
)
def test_bad_parameters_are_one_line_errors(kind, params, needle) -> None:
    with pytest.raises(UserInputError, match=None) as exc:
        build_trajectory(kind, params, REST)
    assert needle in str(exc.value)


def test_csv_times_start_at_zero_and_finite_difference_velocity(tmp_path) -> None:
    path = tmp_path / "late.csv"
    path.write_text("10,0,0,-1\n11,2,0,-1\n12,2,1,-1\n")
    traj = build_trajectory("csv", {"path": str(path), "climb_s": 2.0}, REST)
    assert traj.duration_s == pytest.approx(2.0 + 2.0)
    p = traj.sample(2.0 + 1.0)
    np.testing.assert_allclose(p.position_ned_m, [2.0, 0.0, -1.0])
    np.testing.assert_allclose(p.velocity_ned_mps, [1.0, 0.5, 0.0])  # central difference at a row
    p = traj.sample(2.0 + 0.5)
    np.testing.assert_allclose(p.position_ned_m, [1.0, 0.0, -1.0])
    np.testing.assert_allclose(p.velocity_ned_mps, [1.5, 0.25, 0.0])  # one-sided at row 1, interpolated
    np.testing.assert_allclose(traj.sample(0.0).position_ned_m, [0.0, 0.0, -REST])


@pytest.mark.parametrize("content,needle", [("t,n,e,d\n0,1,2,3\n", "at least 2 rows"),
                                            ("0,0,0,-1\n0,1,0,-1\n", "times must increase"),
                                            ("0,0,0,-1\n1,x,0,-1\n", "not numeric"),
                                            ("0,0,0,-1\n1,0,0,0.2\n", "row 2: down 0.2 is below")])
def test_bad_csv_files(tmp_path, content, needle) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(content)
    with pytest.raises(UserInputError) as exc:
        build_trajectory("csv", {"path": str(path)}, REST)
    assert needle in str(exc.value)


def test_csv_velocity_agrees_with_finite_differences(tmp_path) -> None:
    path = tmp_path / "fine.csv"
    t = np.arange(0.0, 6.0 + 1e-9, 0.05)
    path.write_text("\n".join(f"{a},{math.sin(a)},{0.2 * a},{-1.0 - 0.1 * a}" for a in t))
    traj = build_trajectory("csv", {"path": str(path), "climb_s": 2.0}, REST)
    h = 1e-4
    for t_s in np.linspace(0.1, traj.climb_s - 0.1, 15):  # analytic take-off
        a, b, mid = traj.sample(t_s - h), traj.sample(t_s + h), traj.sample(t_s)
        np.testing.assert_allclose((b.position_ned_m - a.position_ned_m) / (2 * h), mid.velocity_ned_mps, atol=2e-5)
    for tau in t[:-2] + 0.025:  # row midpoints: secant slope of the replayed points = reported velocity
        a, b, mid = traj.sample(2.0 + tau - h), traj.sample(2.0 + tau + h), traj.sample(2.0 + tau)
        np.testing.assert_allclose((b.position_ned_m - a.position_ned_m) / (2 * h), mid.velocity_ned_mps, atol=1e-3)
        np.testing.assert_allclose(mid.velocity_ned_mps, [math.cos(tau), 0.2, -0.1], atol=1e-3)
    np.testing.assert_allclose(traj.sample(traj.climb_s).position_ned_m, [0.0, 0.0, -1.0], atol=1e-12)


def test_hover_defaults_and_take_off_point() -> None:
    traj = build_trajectory("hover", {}, REST)
    assert traj.duration_s == pytest.approx(10.0)
    np.testing.assert_allclose(traj.sample(3.0).position_ned_m, [0.0, 0.0, -2.0 - REST])
    np.testing.assert_allclose(traj.sample(1.5).position_ned_m, [0.0, 0.0, -1.0 - REST])  # min-jerk midpoint
    traj = build_trajectory("hover", {"east_m": -1.5}, REST, start_ned_m=(4.0, 9.0))
    np.testing.assert_allclose(traj.sample(0.0).position_ned_m, [4.0, -1.5, -REST])
    np.testing.assert_allclose(traj.sample(10.0).position_ned_m, [4.0, -1.5, -2.0 - REST])


def test_spiral_parameters_and_hold_after_the_end() -> None:
    traj = build_trajectory("mars-ftcc-spiral", {"k_radps": 1.0, "revolutions": 1}, REST)
    assert traj.duration_s == pytest.approx(2 * math.pi)
    end = traj.sample(traj.duration_s)
    after = traj.sample(traj.duration_s + 5.0)
    np.testing.assert_allclose(after.position_ned_m, end.position_ned_m)
    np.testing.assert_allclose(after.velocity_ned_mps, 0.0)
    assert end.position_ned_m[2] == pytest.approx(-0.1 * 2 * math.pi - REST)


@pytest.mark.parametrize(
    "kind,params,needle",
    [
        ("csv", {}, "kind 'csv' needs 'path'"),
        ("csv", {"path": 3}, "path must be a str"),
        ("waypoints", {"points": "0,0,-1"}, "points must be a list"),
        ("hover", {"height_m": True}, "height_m must be a number"),
        ("hover", {"duration_s": 0}, "duration_s must be > 0"),
        ("waypoints", {"points": [[0, 0, -1]], "cruise_mps": -0.5}, "cruise_mps must be > 0"),
        ("mars-ftcc-spiral", {"T": 0.0}, "T must be > 0"),
        ("mars-ftcc-spiral", {"radius_m": 1.0}, "unknown key 'radius_m' for kind 'mars-ftcc-spiral'"),
    ],
)
def test_more_bad_parameters_name_the_key(kind, params, needle) -> None:
    with pytest.raises(UserInputError) as exc:
        build_trajectory(kind, params, REST)
    assert needle in str(exc.value)
    assert "\n" not in str(exc.value)
