"""Planning maps, SDF, footprint geometry and the optimal-yaw table."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mars_link.core.assembly import AssemblyModel
from mars_link.core.errors import UserInputError
from mars_link.planning.attitude import OptimalYaw, authority, wrap_half_pi
from mars_link.planning.footprint import Footprint, footprint_clearance, rounded_rect_distance
from mars_link.planning.maps import (
    ForestParams,
    ObstacleMap,
    SignedDistanceField,
    load_boxes_csv,
    load_map,
    load_pcd,
    random_forest,
)

HEADER = "cx,cy,length_m,thickness_m,height_m,yaw_deg\n"


def write(tmp_path: Path, name: str, text: str) -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def test_boxes_csv_converted_from_the_scene_frame(tmp_path):
    # yaw 0: length along scene y = north; yaw 90: along scene x = east
    m = load_boxes_csv(write(tmp_path, "w.csv", HEADER + "2.0,10.0,4.0,0.2,2.4,0\n5.0,1.0,2.0,0.2,2.4,90\n"))
    d = m.signed_distance(np.array([
        [11.9, 2.0],   # inside wall 1 near its north end (north = cy + 1.9)
        [10.0, 2.3],   # 0.2 east of wall 1's east face
        [1.0, 5.95],   # inside wall 2 near its east end
        [1.5, 5.0],    # 0.4 north of wall 2's face
    ]))
    assert d[0] < 0 and d[2] < 0
    assert d[1] == pytest.approx(0.2, abs=1e-9)
    assert d[3] == pytest.approx(0.4, abs=1e-9)


def test_boxes_lower_than_the_flight_are_flown_over(tmp_path):
    p = write(tmp_path, "w.csv", HEADER + "0,0,1,0.2,2.4,0\n3,3,1,0.2,1.0,0\n")
    assert len(load_boxes_csv(p, altitude_m=2.3).boxes) == 1
    assert len(load_boxes_csv(p).boxes) == 2


@pytest.mark.parametrize("text, msg", [
    ("x,y\n1,2\n", "header"),
    (HEADER + "1,2,3,4\n", "line 2"),
    (HEADER + "1,2,abc,0.1,2,0\n", "line 2"),
    (HEADER + "1,2,-1,0.1,2,0\n", "must be > 0"),
    (HEADER + "1,2,nan,0.1,2,0\n", "finite"),
    (HEADER, "no obstacle"),
])
def test_malformed_boxes_csv(tmp_path, text, msg):
    with pytest.raises(UserInputError, match=msg):
        load_boxes_csv(write(tmp_path, "bad.csv", text))


def test_bundled_walls_map_of_paper_000():
    from mars_link.planning.pipeline import resolve_data_path

    m = load_boxes_csv(resolve_data_path("paper000_walls.csv"), altitude_m=2.3)
    assert len(m.boxes) == 28
    # the scaled 3.3 m wall at scene (0.15, 5.175), yaw 90, runs along east at north 5.175
    assert m.signed_distance(np.array([[5.175, 1.5]]))[0] < 0
    assert m.signed_distance(np.array([[5.175, 2.5]]))[0] > 0.5


PCD = """# .PCD v0.7
VERSION 0.7
FIELDS x y z
SIZE 4 4 4
TYPE F F F
COUNT 1 1 1
WIDTH {n}
HEIGHT 1
POINTS {n}
DATA ascii
{rows}"""


def test_pcd_points_become_discs_at_the_flight_height(tmp_path):
    rows = "1 2 0.2\n3 4 2.0\n5 6 2.2\n"
    m = load_pcd(write(tmp_path, "m.pcd", PCD.format(n=3, rows=rows)), altitude_m=2.0, band_m=0.5, point_radius_m=0.1)
    assert m.discs.shape == (2, 3)
    np.testing.assert_allclose(m.discs[0], [4.0, 3.0, 0.1])  # north = y, east = x
    assert load_map(tmp_path / "m.pcd").discs.shape == (3, 3)


@pytest.mark.parametrize("text, msg", [
    (PCD.format(n=2, rows="1 2 3\n"), "header says 2"),
    (PCD.format(n=1, rows="1 x 3\n"), "not numeric"),
    (PCD.format(n=1, rows="1 2 3\n").replace("DATA ascii", "DATA binary"), "ascii"),
    ("hello\n", "not an ASCII PCD"),
])
def test_malformed_pcd(tmp_path, text, msg):
    with pytest.raises(UserInputError, match=msg):
        load_pcd(write(tmp_path, "bad.pcd", text))


def test_unknown_map_format(tmp_path):
    with pytest.raises(UserInputError, match="unknown format"):
        load_map(write(tmp_path, "m.txt", "1 2 3"))


def test_forest_is_seeded_and_keeps_start_and_goal_clear():
    p = ForestParams(length_m=30, width_m=10, density_per_100m2=4.0)
    a, start, goal = random_forest(3, p)
    b, _, _ = random_forest(3, p)
    c, _, _ = random_forest(4, p)
    np.testing.assert_array_equal(a.discs, b.discs)
    assert not np.array_equal(a.discs, c.discs)
    assert len(a.discs) == 12
    assert a.signed_distance(np.array([start, goal])).min() >= p.clear_radius_m - 1e-9


def test_sdf_matches_exact_distance_and_its_gradient_is_the_interpolant_s():
    m = ObstacleMap(boxes=np.array([[2.0, 1.0, 1.0, 0.1, 0.3]]), discs=np.array([[-1.0, -1.0, 0.4]]),
                    bounds=(-3.0, 4.0, -3.0, 3.0))
    sdf = SignedDistanceField(m, 0.05)
    rng = np.random.default_rng(1)
    p = rng.uniform([-2.5, -2.5], [3.5, 2.5], (3000, 2))
    value, grad = sdf.query(p)
    assert np.max(np.abs(value - m.signed_distance(p))) < 0.05
    assert value[np.argmin(m.signed_distance(p))] < 0  # inside is negative
    h = 1e-6
    frac = ((p - sdf.origin) / sdf.resolution_m) % 1.0
    p = p[np.all((frac > 1e-3) & (frac < 1 - 1e-3), axis=1)]  # not on a cell edge (the interpolant has kinks there)
    grad = sdf.query(p)[1]
    for axis in range(2):
        dp = np.zeros(2)
        dp[axis] = h
        fd = (sdf.query(p + dp)[0] - sdf.query(p - dp)[0]) / (2 * h)
        np.testing.assert_allclose(grad[:, axis], fd, atol=1e-4)


def test_rounded_rectangle_distance_known_cases():
    sq = lambda n, e, ang=0.0, r=0.0: [n, e, 0.5, 0.5, ang, r]
    a = np.array([sq(0, 0), sq(0, 0), sq(0, 0), sq(0, 0), [0, 0, 0, 0, 0, 0.3]])
    b = np.array([sq(0, 2), sq(2, 2), sq(0, 0.8), [0, 1.5, 0, 0, 0, 0.2], sq(0, 1.0, 0.0)])
    d = rounded_rect_distance(a, b)
    np.testing.assert_allclose(d, [1.0, math.sqrt(2.0), -0.2, 0.8, 0.2], atol=1e-12)


@pytest.mark.parametrize("layout, preset", [("XXX,XXX", "mars-ftcc"), ("XX.,.XX", "modquad-cf2"), ("XXXX", "mars-ftcc")])
def test_exact_footprint_clearance_against_dense_sampling(layout, preset):
    model = AssemblyModel.from_layout(layout, preset)
    fp = Footprint.from_model(model)
    scale = model.vehicle.pitch_m / 0.35
    m = ObstacleMap(boxes=np.array([[1.0, 0.5, 0.6, 0.08, 0.4], [-0.5, -1.0, 0.3, 0.3, 0.0]]) * [scale] * 4 + [0, 0, 0, 0, 0],
                    discs=np.array([[0.2, -0.2, 0.1]]) * scale)
    rng = np.random.default_rng(2)
    poses = np.column_stack([rng.uniform(-1.5, 1.5, (150, 2)) * scale, rng.uniform(-np.pi, np.pi, 150)])
    exact = footprint_clearance(fp, m, poses, near_m=10.0)
    dense = fp.body_points(0.002 * scale, 0.01 * scale)  # outline and interior, finely
    brute = []
    for q in poses:
        c, s = math.cos(q[2]), math.sin(q[2])
        w = q[:2] + dense @ np.array([[c, s], [-s, c]])
        brute.append(m.signed_distance(w).min())
    brute = np.array(brute)
    apart = brute > 0
    assert np.max(np.abs(exact[apart] - brute[apart])) < 0.003 * scale
    assert np.all(exact[~apart] < 1e-9)  # overlap is never reported as clearance
    assert apart.any() and (~apart).any()


def test_optimal_yaw_counts_faults_and_is_pi_periodic():
    model = AssemblyModel.from_layout("XXXX")
    eta = model.nominal_eta()
    healthy = authority(model, eta, np.linspace(0, np.pi, 7))
    eta[model.unit_slots(3)] = 0.0
    faulty = authority(model, eta, np.linspace(0, np.pi, 7))
    assert np.all(faulty <= healthy + 1e-12) and np.any(faulty < healthy - 1e-6)
    a = np.linspace(0, np.pi, 5)
    np.testing.assert_allclose(authority(model, eta, a), authority(model, eta, a + np.pi))
    star = OptimalYaw(model, eta)
    # a 4x1 (units along body y) tilts fastest about its long axis: fly broadside (travel along body x)
    assert abs(wrap_half_pi(star.alpha_star)) < 1e-9
    h = np.array([0.3, 2.0])
    np.testing.assert_allclose(wrap_half_pi(h - star(h)), 0.0, atol=1e-9)
