"""The GNSS antenna's lever arm: GPS fixes are the antenna's phase centre, the trajectory is the
camera centre. camera.yaml's ``gps_antenna_m`` = [forward, left, up] (m) places the antenna in
the vehicle frame (ISO 8855 axes) relative to the camera; every fix is moved onto the camera
centre before the pose graph sees it (``cam_from_antenna``).

A survey vehicle's antenna sits on the roof, often 1-2 m behind and 0.5-1.5 m above a
front-mounted camera. Left out, the map lies that far along the track and the heights that much
high, and on a turn the offset swings with the heading and bends the track.

First pass (``cam_from_antenna``): the vehicle's axes come from the GPS track itself: forward is the antenna's direction of travel
(the chord of the track over a stretch of path around the fix, long enough for the fixes' noise,
with the slope from the altitudes where the log has them), up is vertical in the plane of
travel. That is the vehicle's heading where the antenna rides over the point that does not slide
sideways (a car's rear axle); an antenna d metres ahead of or behind it moves at d / R off the
heading on a curve of radius R (1 m on a 50 m curve: 1.1°, 3.6 cm on a 1.8 m arm). The
vehicle's roll (the road's cross-fall, body roll) is not known here: an antenna 1.5 m above the
camera on a 2 % cross-fall is placed 3 cm off sideways. Second pass (``cam_from_antenna_posed``,
after the pose graph has solved once): the vehicle's axes from the solved camera rotations and
the mount, wherever on the vehicle the antenna rides.
"""

from __future__ import annotations

import logging

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from roadsurf.core.geometry import check_shape, vehicle_from_flu

log = logging.getLogger(__name__)

# the chord giving a fix's direction of travel spans at least this much path on each side (m):
# a 2 cm RTK fix's noise is then 0.3° of direction (1 cm on a 1.8 m arm; 2 m: 1.8 cm). For a
# circle the chord is parallel to the tangent at its middle, whatever its length
MIN_HALF_CHORD_M = 5.0
# ... and at least this many times the fixes' σ (a 0.5 m fix: 5 m each side, about 0.1 rad of
# direction and slope, 20-30 cm on a 1.8 m arm, inside its own σ)
HALF_CHORD_SIGMAS = 10.0
# a chord whose ends lie closer than this share of its path is no direction (a vehicle standing
# still: its fixes' noise walks back and forth)
MIN_STRAIGHTNESS = 0.5
MAX_SLOPE = 0.3  # the slope along the travel is clipped to this (m/m): 17°, beyond any road


def travel_axes(
    enu_m: np.ndarray, sigma_m: np.ndarray, has_alt: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(forward (G, 3) unit vectors in ENU, ok (G,) bool) along a GPS track: each fix's
    direction of travel, the derivative at the fix of a quadratic in path length fitted to the
    fixes within ±max(``MIN_HALF_CHORD_M``, ``HALF_CHORD_SIGMAS`` σ) of path (the window slid
    inwards at the track's ends, so a curve does not bias them). Fixes where the window's
    track is no direction (a stop, the track shorter than the window) take the nearest fix's
    that is; ``ok`` is False everywhere when no fix has one. enu_m (G, 3) m, sigma_m (G,) m,
    has_alt (G,) bool (the slope uses the altitudes only where every fix of the window has
    one)."""
    P = check_shape("enu_m", np.asarray(enu_m, float), (None, 3))
    n = len(P)
    fwd = np.zeros((n, 3))
    ok = np.zeros(n, bool)
    if n < 3:
        return fwd, ok
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(P[:, :2], axis=0), axis=1))])
    half = np.maximum(MIN_HALF_CHORD_M, HALF_CHORD_SIGMAS * np.asarray(sigma_m, float))
    alt = np.asarray(has_alt, bool)
    for i in range(n):
        a = min(max(s[i] - half[i], s[0]), max(s[-1] - 2 * half[i], s[0]))
        lo = int(np.searchsorted(s, a, side="left"))
        hi = int(np.searchsorted(s, a + 2 * half[i], side="right")) - 1
        if hi - lo < 2 or s[hi] - s[lo] < half[i]:
            continue
        d = P[hi] - P[lo]
        if float(np.hypot(d[0], d[1])) < MIN_STRAIGHTNESS * (s[hi] - s[lo]):
            continue  # the fixes' noise walking about a stop
        u = s[lo : hi + 1] - s[i]
        A = np.column_stack([np.ones_like(u), u, u * u])
        coef = np.linalg.lstsq(A, P[lo : hi + 1], rcond=None)[0]
        v = coef[1].copy()  # d(position)/ds at the fix
        horiz = float(np.hypot(v[0], v[1]))
        if horiz < 1e-9:
            continue
        slope = v[2] / horiz if alt[lo : hi + 1].all() else 0.0
        v = np.array([v[0] / horiz, v[1] / horiz, float(np.clip(slope, -MAX_SLOPE, MAX_SLOPE))])
        fwd[i] = v / np.linalg.norm(v)
        ok[i] = True
    if not ok.any():
        return fwd, ok
    good = np.flatnonzero(ok)
    # the nearest fix with a direction along the path (s never decreases: O(N log N) memory-flat)
    j = np.clip(np.searchsorted(s[good], s), 1, len(good) - 1) if len(good) > 1 else None
    if j is None:
        nearest = np.full(n, good[0])
    else:
        left_closer = np.abs(s - s[good[j - 1]]) <= np.abs(s[good[j]] - s)
        nearest = np.where(left_closer, good[j - 1], good[j])
    fwd[~ok] = fwd[nearest[~ok]]
    return fwd, np.ones(n, bool)


def cam_from_antenna(
    enu_m: np.ndarray, sigma_m: np.ndarray, has_alt: np.ndarray, arm_flu_m: np.ndarray
) -> np.ndarray:
    """(G, 3) camera centres in ENU (m) from antenna positions enu_m (G, 3) m: c = a − R_world_
    from_vehicle · arm, arm_flu_m (3,) = [forward, left, up] (m) of the antenna from the camera
    in the vehicle frame, the vehicle's forward axis from ``travel_axes`` and no roll. Without
    any direction of travel (a static log) only the up component is applied, with a log line."""
    P = check_shape("enu_m", np.asarray(enu_m, float), (None, 3))
    arm = check_shape("arm_flu_m", np.asarray(arm_flu_m, float), (3,))
    fwd, ok = travel_axes(P, sigma_m, has_alt)
    out = P.copy()
    if not ok.any():
        if np.hypot(arm[0], arm[1]) > 0:
            log.info("gps antenna: the track gives no direction of travel; only its height applied")
        out[:, 2] -= arm[2]
        return out
    left = np.column_stack([-fwd[:, 1], fwd[:, 0], np.zeros(len(P))])
    left /= np.linalg.norm(left, axis=1, keepdims=True)
    up = np.cross(fwd, left)
    return out - (arm[0] * fwd + arm[1] * left + arm[2] * up)


def cam_from_antenna_posed(
    antenna_enu_m: np.ndarray,
    t_fix_s: np.ndarray,
    t_s: np.ndarray,
    world_from_cam: np.ndarray,
    R_vehicle_from_cam: np.ndarray,
    arm_flu_m: np.ndarray,
) -> np.ndarray:
    """(G, 3) camera centres in ENU (m) from antenna positions antenna_enu_m (G, 3) m at times
    t_fix_s (G,) s: c = a − R_world_from_vehicle(t) · arm, the vehicle's rotation from the
    frames' solved poses world_from_cam (N, 4, 4) at times t_s (N,) s (spherical interpolation,
    held at the ends) and the mount R_vehicle_from_cam (3, 3) (vehicle x right, y backward, z
    down); arm_flu_m (3,) = [forward, left, up] m. Unlike the track's direction this is the
    vehicle's heading wherever the antenna rides: on a 12 m-radius curve an antenna 1.5 m
    behind the point that does not slide moves 7° off it."""
    A = check_shape("antenna_enu_m", np.asarray(antenna_enu_m, float), (None, 3))
    W = check_shape("world_from_cam", np.asarray(world_from_cam, float), (None, 4, 4))
    arm_vehicle = vehicle_from_flu(arm_flu_m)
    t = np.asarray(t_s, float)
    R_wv = W[:, :3, :3] @ np.asarray(R_vehicle_from_cam, float).T
    if len(t) == 1:
        return A - R_wv[0] @ arm_vehicle
    tq = np.clip(np.asarray(t_fix_s, float), t[0], t[-1])
    R = Slerp(t, Rotation.from_matrix(R_wv))(tq).as_matrix()
    return A - R @ arm_vehicle
