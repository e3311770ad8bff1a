"""The camera's mount on the vehicle: given in camera.yaml, or estimated from the drive.

Every ok pair measures two mount directions in its camera-a coordinates: the road normal of
its plane fit (the vehicle's "up", since the vehicle sits on the road) and the direction of
travel (camera b's centre seen from camera a). Their robust means over the drive give
R_vehicle_from_cam (``core.geometry.vehicle_from_up_forward``). Vibration, grade, cross-fall
and the vehicle's turning average out along a drive; what is left is the mount. Only its yaw and a pitch beyond the range of road grades
are taken from the drive: its roll cannot be told from the road's cross-fall, nor a small
pitch from the grade (``resolve``).

The pose graph then holds the mount's up axis vertical (tilt prior) and its forward axis on
the GPS heading (eq. 6.1). A camera.yaml mount is used as given, but checked against the
drive's own estimate: a disagreement beyond ``mount_disagree_deg`` is a warning with both
values.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from roadsurf.core.fits import MAD_TO_SIGMA
from roadsurf.core.geometry import (
    forward_in_cam,
    mount_angles_deg,
    up_in_cam,
    vehicle_from_cam_rotation,
    vehicle_from_up_forward,
)
from roadsurf.reconstruction.consensus import plane_normal_cam

if TYPE_CHECKING:
    from roadsurf.core.camera import Camera
    from roadsurf.reconstruction.types import PairResult

log = logging.getLogger(__name__)

MIN_PAIRS = 3  # fewer ok pairs than this: an estimate that says it rests on few pairs
MIN_BASELINE_M = 0.01  # pairs that barely moved give no direction of travel (m)


@dataclass
class Mount:
    """The mount used by the run and where it came from (goes to report.json)."""

    R_vehicle_from_cam: np.ndarray  # (3, 3)
    source: str  # "camera.yaml" | "estimated" | "assumed nadir"
    estimated_deg: tuple[float, float, float] | None = None  # (pitch, roll, yaw) from the drive
    spread_deg: float | None = None  # robust σ of the pairs' road normals about the estimate
    n_pairs: int = 0
    warnings: list[str] = field(default_factory=list)

    @property
    def angles_deg(self) -> tuple[float, float, float]:
        """(pitch, roll, yaw) degrees of the mount used."""
        return mount_angles_deg(self.R_vehicle_from_cam)

    def to_dict(self) -> dict[str, Any]:
        p, r, y = self.angles_deg
        return {
            "pitch_deg": round(p, 3),
            "roll_deg": round(r, 3),
            "yaw_deg": round(y, 3),
            "source": self.source,
            "estimated_deg": None
            if self.estimated_deg is None
            else [round(a, 3) for a in self.estimated_deg],
            "normal_spread_deg": None
            if self.spread_deg is None or not math.isfinite(self.spread_deg)
            else round(self.spread_deg, 3),
            "n_pairs": self.n_pairs,
        }


def _unit_median(v: np.ndarray) -> np.ndarray:
    """Component-wise median of (N, 3) unit vectors, renormalised (robust to a few outliers)."""
    m = np.median(v, axis=0)
    return m / np.linalg.norm(m)


def heading_at_a(
    R_b_from_a: np.ndarray, c_b: np.ndarray, up: np.ndarray | None = None
) -> np.ndarray:
    """(3,) unit direction of travel at camera a, in camera a, from camera b's centre c_b (3,)
    in camera a (m) and the pair's rotation. On a turn the chord a -> b points along the
    heading half-way through the turn (a circular arc): it is turned back by half the pair's
    turn (R_a_from_b = Rot(θ) -> Rot(θ/2)⁻¹), else a one-way turn biased the mount's yaw by
    half the turn per pair (a 40 m U-turn: 2.5°, and every exported heading with it). With
    ``up`` (3,) (the road normal in camera a) only the turn about it counts: the vibration's
    pitch and roll between the frames do not bend the path."""
    from scipy.spatial.transform import Rotation

    if up is None:
        rv = Rotation.from_matrix(np.asarray(R_b_from_a, float).T).as_rotvec()
    else:
        u = np.asarray(up, float) / np.linalg.norm(up)
        rv = turn_about_rad(R_b_from_a, u) * u
    f = Rotation.from_rotvec(rv / 2.0).inv().apply(np.asarray(c_b, float))
    return f / np.linalg.norm(f)


def turn_about_rad(R_b_from_a: np.ndarray, axis: np.ndarray) -> float:
    """Signed angle (rad) of camera b's rotation from camera a (R_a_from_b) about ``axis``
    (3,) in camera a: a pair's turn about its road normal, without the vibration's roll and
    pitch between the frames."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(np.asarray(R_b_from_a, float).T).as_rotvec()
    u = np.asarray(axis, float)
    return float(rv @ u) / float(np.linalg.norm(u))


def estimate_from_pairs(
    pairs: list[PairResult],
) -> tuple[np.ndarray, float, int] | None:
    """(R_vehicle_from_cam (3, 3), spread of the road normals (deg), pairs used) from the ok
    pairs' road planes and directions of travel, or None without a usable pair. One pair
    counts: its plane fit (hundreds of road points) holds the tilt to a fraction of a degree,
    where assuming nadir for a 45° camera (a two-frame photo pair) puts the road 45° off."""
    ups, fwds = [], []
    for p in pairs:
        if not p.ok:
            continue
        pl = np.asarray(p.plane, float)
        T = p.cam_b_from_cam_a
        c_b = -T[:3, :3].T @ T[:3, 3]  # camera b's centre in camera a (m)
        if not np.all(np.isfinite(pl)) or not np.all(np.isfinite(c_b)):
            continue
        if float(np.linalg.norm(c_b)) < MIN_BASELINE_M:
            continue
        up = -plane_normal_cam(pl)  # towards the camera
        ups.append(up)
        fwds.append(heading_at_a(T[:3, :3], c_b, up))
    if not ups:
        return None
    U, F = np.array(ups), np.array(fwds)
    up = _unit_median(U)
    # the direction of travel: the vehicle may drive backwards in a test; take the dominant one
    fwd = _unit_median(F)
    R = vehicle_from_up_forward(up, fwd)
    ang = np.degrees(np.arccos(np.clip(U @ up, -1.0, 1.0)))
    # one pair agrees with itself: no spread to report
    spread = float(MAD_TO_SIGMA * np.median(ang)) if len(ang) >= 2 else float("nan")
    return R, spread, len(ups)


def resolve(
    camera: Camera,
    pairs: list[PairResult],
    *,
    estimate: bool,
    disagree_deg: float,
    min_pitch_deg: float = 0.0,
    grade_known: float = 0.0,
) -> Mount:
    """The mount for this run: camera.yaml's when given (checked against the drive's estimate),
    else the estimate when ``estimate`` and at least one usable pair (a warning below
    ``MIN_PAIRS``), else nadir with a warning when the pairs say otherwise."""
    est = estimate_from_pairs(pairs)
    est_R, spread, n = (None, None, 0) if est is None else est
    est_deg = None if est_R is None else mount_angles_deg(est_R)
    warns: list[str] = []
    if camera.mount_deg is not None:
        R = vehicle_from_cam_rotation(*camera.mount_deg)
        m = Mount(R, "camera.yaml", est_deg, spread, n)
        if est_R is not None:
            # yaw is the weakest part of the estimate (turns, crabbing): compare the up axes and
            # the forward axes separately
            d_up = _angle_deg(up_in_cam(R), up_in_cam(est_R))
            d_fwd = _angle_deg(forward_in_cam(R), forward_in_cam(est_R))
            if max(d_up, d_fwd) > disagree_deg:
                warns.append(
                    "camera.yaml mount (pitch, roll, yaw) = "
                    f"{_fmt(camera.mount_deg)} deg disagrees with the drive's road planes, which "
                    f"give {_fmt(est_deg)} deg (up axes {d_up:.1f} deg apart, forward axes "
                    f"{d_fwd:.1f} deg apart; > {disagree_deg} deg). Check the mount angles, "
                    "or remove them from camera.yaml to use the estimate."
                )
    elif estimate and est_R is not None and est_deg is not None:
        # Roll is kept at 0: the road normals cannot tell a rolled mount from the road's
        # cross-fall (a 2.5 % crown is 1.4°), and GPS cannot observe roll on a straight drive.
        # Pitch below min_pitch_deg is kept at 0 too: there a forward mount and the drive's
        # mean grade look the same (an 8.7 % grade is 5°), and the tilt prior's σ and the GPS
        # heights absorb a small real one. Yaw (from the direction of travel) is kept.
        pitch, roll, yaw = est_deg
        # ... unless the GPS heights resolve the grade (grade_known: the share of the fitted
        # grade the tilt prior keeps, mapping.grade): the estimate is the pitch against the
        # road, the prior then adds the grade, and the two no longer look the same
        small = pitch * min(max(grade_known, 0.0), 1.0)
        applied = pitch if abs(pitch) >= min_pitch_deg else small
        # A roll beyond any road's cross-fall (disagree_deg) is mostly the mount's: applied,
        # the error left is the cross-fall (2 %: 1.1°, 22 mm sideways at 1.1 m), where
        # keeping 0 left the whole roll (3°: the map 59 mm sideways, benchmarks/variation.py)
        big_roll = abs(roll) > disagree_deg
        R = vehicle_from_cam_rotation(applied, roll if big_roll else 0.0, yaw)
        m = Mount(R, "estimated", est_deg, spread, n)
        log.info("mount estimated from %d pairs: (pitch, roll, yaw) = %s deg", n, _fmt(est_deg))
        if n < MIN_PAIRS:
            warns.append(
                f"the mount {_fmt(est_deg)} deg (pitch, roll, yaw) rests on {n} pair(s) only "
                f"(a robust estimate needs {MIN_PAIRS}): a pair's vibration or a local slope "
                "goes into the map's tilt. Give the mount in camera.yaml "
                "(`roadsurf calibrate --ground`) for a short sequence."
            )
        if big_roll:
            shift = camera.height_m * math.tan(math.radians(abs(roll)))
            warns.append(
                f"the drive's road planes give a camera roll of {roll:.1f} deg (more than a "
                f"road's cross-fall; > {disagree_deg} deg), applied. The road planes cannot "
                "tell a rolled mount from the road's cross-fall: the part of it that is "
                "cross-fall moves the map sideways (each 1 % of cross-fall 0.57 deg, "
                f"{100 * camera.height_m * 0.01:.1f} cm at this height; {100 * shift:.0f} cm if "
                "all of it is, as on a banked curve), while ignoring a real mount roll would "
                f"move it {100 * shift:.0f} cm. Measure it (`roadsurf calibrate --ground`) and "
                "set mount_roll_deg in camera.yaml."
            )
    else:
        m = Mount(np.eye(3), "assumed nadir", est_deg, spread, n)
        if est_R is not None and _angle_deg(up_in_cam(est_R), up_in_cam(np.eye(3))) > disagree_deg:
            warns.append(
                f"the camera is assumed nadir, but the drive's road planes give a mount of "
                f"{_fmt(est_deg)} deg (pitch, roll, yaw). Set mount_pitch_deg/mount_roll_deg/"
                "mount_yaw_deg in camera.yaml or enable mapping.estimate_mount."
            )
    for w in warns:
        log.warning("mount: %s", w)
    m.warnings = warns
    return m


def _angle_deg(a: np.ndarray, b: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b), -1.0, 1.0))))


def _fmt(a: tuple[float, float, float] | None) -> str:
    return "?" if a is None else "(" + ", ".join(f"{x:.1f}" for x in a) + ")"
