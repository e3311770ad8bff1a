import math

import numpy as np
import pytest

from roadsurf.core.geometry import (
    EnuReference,
    ExportFrame,
    enu_from_lla,
    heading_deg_from_displacement,
    heading_deg_from_world_rotation,
    invert_pose,
    lla_from_enu,
    skew,
    transform_points,
    utm_epsg_for,
    utm_exception_key,
    world_from_cam,
)


def test_enu_round_trip_and_scale():
    ref = EnuReference(43.65, -79.38, 80.0)
    rng = np.random.default_rng(0)
    enu = rng.uniform(-2000, 2000, size=(50, 3))
    enu[:, 2] = rng.uniform(-5, 5, 50)
    lla = lla_from_enu(enu, ref)
    back = enu_from_lla(lla[:, 0], lla[:, 1], lla[:, 2], ref)
    np.testing.assert_allclose(back, enu, atol=1e-6)
    # 1e-3 degree of latitude is about 111 m north.
    d = enu_from_lla(43.651, -79.38, 80.0, ref)[0]
    assert abs(d[1] - 111.1) < 0.5 and abs(d[0]) < 1e-6


def test_utm_zone_and_export_distances():
    assert utm_epsg_for(43.65, -79.38) == 32617
    assert utm_epsg_for(-33.9, 151.2) == 32756
    # the grid's exceptions: Bergen is in 32N, Svalbard has only the odd zones 31-37
    assert utm_epsg_for(60.39, 5.32) == 32632 and utm_epsg_for(60.39, 2.9) == 32631
    assert utm_epsg_for(55.9, 5.32) == 32631
    svalbard = [(8.9, 32631), (9.0, 32633), (20.5, 32633), (21.0, 32635), (33.0, 32637)]
    assert [utm_epsg_for(78.2, lon) for lon, _ in svalbard] == [e for _, e in svalbard]
    assert utm_epsg_for(78.2, 42.5) == 32638
    # the resume keys change only where the exceptions apply
    assert utm_exception_key(43.65, -79.38) == "" and utm_exception_key(78.2, 15.6) == ""
    assert utm_exception_key(60.39, 5.32) == "utm:32632"
    ef = ExportFrame.for_reference(EnuReference(43.65, -79.38, 0.0))
    pts = np.array([[0.0, 0.0, 0.0], [30.0, 40.0, 0.0]])
    utm = ef.utm_from_enu(pts)
    # Distances are preserved to the UTM scale factor (< 0.1 %).
    assert abs(np.linalg.norm(utm[1, :2] - utm[0, :2]) - 50.0) < 0.05
    lonlat = ef.lonlat_from_enu(pts)
    assert np.allclose(lonlat[0], [-79.38, 43.65])


def test_camera_axes_follow_heading():
    # Heading east: camera x (vehicle right) points south, camera y (backward) points west.
    T = world_from_cam(90.0, position_enu_m=np.array([1.0, 2.0, 3.0]))
    np.testing.assert_allclose(T[:3, 0], [0, -1, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 1], [-1, 0, 0], atol=1e-12)
    np.testing.assert_allclose(T[:3, 2], [0, 0, -1], atol=1e-12)
    assert heading_deg_from_world_rotation(T[:3, :3]) == pytest.approx(90.0)
    assert np.isclose(np.linalg.det(T[:3, :3]), 1.0)
    # A point 1 m below the camera is 1 m lower in the world.
    assert np.allclose(transform_points(T, np.array([[0, 0, 1.0]])), [[1, 2, 2]])
    np.testing.assert_allclose(invert_pose(T) @ T, np.eye(4), atol=1e-12)


def test_heading_from_displacement_matches_eq_6_1():
    # Eq. 6.1 gives θ = atan2(-dx, dy), counter-clockwise from north; compass heading is -θ.
    dx, dy = np.array([1.0, 0.0, -1.0]), np.array([0.0, 1.0, -1.0])
    h = heading_deg_from_displacement(dx, dy)
    np.testing.assert_allclose(h, [90.0, 0.0, 225.0])
    theta = np.degrees(np.arctan2(-dx, dy))
    np.testing.assert_allclose((-theta) % 360, h)


def test_shape_checks():
    with pytest.raises(ValueError, match=r"expected shape \(3,\)"):
        skew(np.zeros(4))
    with pytest.raises(ValueError, match=r"expected shape \(N, 3\)"):
        transform_points(np.eye(4), np.zeros((5, 2)))


@pytest.mark.parametrize(
    "a, b",
    [
        ([0.0, 0.0, 1.0], [0.3, -0.2, 0.9]),
        ([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]),  # the same: identity
        ([0.0, 0.0, 1.0], [0.0, 0.0, -1.0]),  # opposite: a half turn, not the identity
        ([1.0, 0.0, 0.0], [-2.0, 0.0, 0.0]),
        ([0.2, 0.5, -0.8], [-0.2, -0.5, 0.8]),
    ],
)
def test_rotation_b_from_a_is_a_proper_rotation_onto_b(a: list[float], b: list[float]) -> None:
    from roadsurf.core.geometry import rotation_b_from_a

    R = rotation_b_from_a(np.array(a), np.array(b))
    an, bn = np.array(a) / np.linalg.norm(a), np.array(b) / np.linalg.norm(b)
    assert R @ an == pytest.approx(bn, abs=1e-12)
    assert R.T @ R == pytest.approx(np.eye(3), abs=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    # the smallest rotation: its angle is the angle between a and b
    ang = math.acos(np.clip((np.trace(R) - 1) / 2, -1, 1))
    assert ang == pytest.approx(math.acos(np.clip(an @ bn, -1, 1)), abs=1e-7)
