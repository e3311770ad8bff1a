"""Simulator configuration: one frozen dataclass, every field with its unit and, where the
dissertation names it (Chapter 3), its symbol. Scenarios (``simulation.scenarios``) are named sets
of overrides of these fields; ``simulate(..., **overrides)`` accepts any field by name."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np

from roadsurf.core.camera import RENDER_UNDISTORT_CRITERIA, Camera
from roadsurf.core.errors import ConfigError
from roadsurf.core.geometry import vehicle_from_cam_rotation

MIN_DEPRESSION_DEG = 10.0  # every image-border ray must look this far below the horizon (deg)

GpsProfile = Literal["rtk", "consumer"]
Texture = Literal["gravel", "asphalt", "brick", "grass"]
ImageFormat = Literal["jpg", "png"]


@dataclass(frozen=True)
class SimConfig:
    """Parameters of one rendered drive (image level)."""

    # --- world placement -------------------------------------------------------------------
    origin_lat_deg: float = 43.6532  # latitude of the route start (WGS84 degrees), Toronto
    origin_lon_deg: float = -79.3832  # longitude of the route start (WGS84 degrees)
    origin_alt_m: float = 95.0  # ellipsoidal height of the road at the start (m)
    route_heading_deg: float | None = None  # grid heading at the start (deg); None = from seed
    route_curve_amp_deg: float = 8.0  # amplitude of the heading oscillation (deg): gentle curve
    route_curve_wavelength_m: float = 180.0  # wavelength of the heading oscillation (m)
    lateral_wander_m: float = 0.04  # std of the camera's slow lateral wander in the lane (m)

    # --- camera (intrinsics; camera.yaml) -------------------------------------------------
    width: int = 640  # image width (px)
    height: int = 480  # image height (px)
    fx: float = 600.0  # focal length (px); fy = fx (square pixels)
    camera_height_m: float = 1.1  # nominal camera-to-road distance Z_m = h (m)
    fps: float = 15.0  # frame rate (Hz)
    distortion: tuple[float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0)  # OpenCV
    # k1, k2, p1, p2, k3 of the rendered lens (written to camera.yaml `dist`)

    # --- camera mount (core.geometry.vehicle_from_cam_rotation; all 0 = nadir) -------------
    mount_pitch_deg: float = 0.0  # optical axis tilted forward from nadir (deg)
    mount_roll_deg: float = 0.0  # optical axis tilted to the vehicle's right (deg)
    mount_yaw_deg: float = 0.0  # camera turned clockwise seen from above (deg)
    write_mount: bool = False  # write the mount angles to camera.yaml; off by default: users
    # rarely know them and the pipeline estimates them

    # --- shutter ----------------------------------------------------------------------------
    readout_s: float = 0.0  # rolling shutter: the sensor reads its rows top to bottom in this
    # time (s), row v from the pose at the frame's timestamp + readout_s * v / height (written
    # to camera.yaml); 0 = global shutter, every row from the timestamp's pose

    # --- motion ------------------------------------------------------------------------------
    speed_mps: float = 6.0  # mean vehicle speed (m/s); overlap = 1 - speed/(fps * footprint)
    speed_var: float = 0.04  # relative slow speed variation (std, fraction of speed)
    vibration_deg: float = 0.3  # std of roll and pitch noise θx, θy (deg)
    yaw_noise_deg: float = 0.15  # std of yaw noise θz about the road heading (deg)
    height_noise_m: float = 0.003  # std of camera height noise δ_h (m)
    vibration_hz: float = 3.0  # dominant frequency of the vibration (Hz)
    # the vehicle's body rolls with the road across its wheels (TRACK_M; cross slope and
    # long-wave undulation), as a real one does: a 2 % cross slope rolls it 1.15°. Off by
    # default: the reference drives keep a level body (docs/simulator.md)
    roll_with_road: bool = False
    revisit_after_s: float = 0.0  # > 0: a revisit (a survey that comes back along the same
    # lane): the second half of the frames drives the first half's road again, starting this
    # long (s) after the first half ends (between the passes no frames; the logs follow the
    # road back); 0 = one pass

    # --- road surface ------------------------------------------------------------------------
    unevenness_m: float = 0.0015  # road unevenness δ: height ~ N(0, δ), correlated over ~1 cm (m)
    grade: float = 0.01  # longitudinal grade (m/m)
    cross_slope: float = 0.02  # cross slope of the smooth road (m/m)
    undulation_m: float = 0.01  # amplitude of long-wave (>= 8 m) smooth road undulation (m)
    n_potholes: int = 3  # number of potholes (irregular bowls, 15-80 mm deep, 0.15-0.8 m across)
    # pothole look and shape: albedo factor inside (< 1 darker, > 1 lighter, e.g. fresh
    # aggregate) and the wall exponent p of D(1 - ρ^p) (larger = steeper wall, flatter bottom)
    pothole_darken: tuple[float, float] = (0.55, 0.8)  # range of the albedo factor (ratio)
    pothole_power: tuple[float, float] = (2.5, 5.0)  # range of the profile exponent p (-)
    pothole_size_m: tuple[float, float] = (0.15, 0.8)  # range of the sizes across (m), drawn
    # stratified so a drive holds small and large ones
    pothole_depth_m: tuple[float, float] = (0.015, 0.08)  # range of the maximum depths (m)
    n_cracks: int = 1  # number of cracks (grooves 3-8 mm wide, a few mm deep)
    n_ruts: int = 0  # number of ruts (long shallow troughs)
    n_lane_markings: int = 1  # number of lane-marking groups (white paint, no depth)
    marking_style: Literal["mixed", "dashed", "stop_bar"] = "mixed"  # lane-marking groups are
    # dashed longitudinal lines, transverse stop bars, or a mix (70% dashed)
    n_shadows: int = 1  # number of shadows (darker radiance only, no depth)
    n_oil_stains: int = 1  # number of oil stains (dark albedo, no depth)
    defect_margin_m: float = 1.0  # keep defects this far from the drive's ends (m)

    # --- appearance --------------------------------------------------------------------------
    texture: Texture = "gravel"  # skimage photo texture used for the albedo
    texel_m: float = 0.0005  # ground size of one texture pixel (m) before random scaling
    texture_cell_m: float = 0.3  # size of the random rotation/scale cells (m)
    sun_azimuth_deg: float = 135.0  # light direction: compass azimuth (deg)
    sun_elevation_deg: float = 45.0  # light direction: elevation above the horizon (deg)
    ambient: float = 0.4  # share of diffuse sky light (0..1); the rest is directional
    cloud_shadow: float = 0.0  # max share of direct light blocked by soft cloud shadows (0..1)
    exposure: float = 1.0  # global brightness gain
    exposure_var: float = 0.03  # per-frame auto-exposure variation (std, relative)
    vignetting: float = 0.2  # brightness fall-off at the image corner (fraction)
    noise_sigma: float = 2.0  # sensor read noise (std, 8-bit DN)
    shot_noise: float = 0.25  # photon noise gain (DN std = shot_noise * sqrt(DN))
    exposure_time_s: float = 0.0005  # shutter time (s): motion blur = speed * exposure_time
    motion_blur: bool = True  # apply motion blur when it exceeds 0.3 px
    image_format: ImageFormat = "jpg"  # frame file format
    jpeg_quality: int = 90  # JPEG quality (0-100)
    greyscale: bool = False  # write 8-bit single-channel images

    # --- image-fixed overlays (simulation.overlay; in the image only, never in the truth) ---
    overlay_text: bool = False  # a burned-in date/time/speed stamp: an opaque black box with
    # white text in the top-left corner (35 % of the width, 6 % of the height, >= 12 px),
    # fixed in the image; its text changes per frame
    hood_share: float = 0.0  # the vehicle's bonnet over the bottom of the image: its top edge
    # is this share of the image height (-) above the bottom edge at the centre, a gentle
    # curve lower towards the sides; 0 = none
    write_mask: bool = False  # write DRIVE/mask.png (uint8, 0 = the overlay pixels dilated by
    # 2 px, 255 = usable) and `mask: mask.png` in camera.yaml; truth/mask.png is written with
    # any overlay whether or not this is set

    # --- rendering ---------------------------------------------------------------------------
    supersample: int = 2  # rays per pixel along each axis (anti-aliasing)
    render_gsd_m: float | None = None  # world raster resolution (m); None = pixel footprint / 1.5
    raycast_iters: int = 4  # fixed-point iterations of the ray/height-field intersection
    truth_gsd_m: float = 0.004  # ground-truth raster resolution (m)

    # --- sensors -----------------------------------------------------------------------------
    gps_format: Literal["csv", "gpx", "nmea"] = "csv"  # GPS log file: gps.csv, gps.gpx, gps.nmea
    start_utc: str = "2026-06-15T14:00:00+00:00"  # recording start (ISO 8601); with gpx/nmea
    # every timestamp of the drive is UNIX seconds (UTC) from it, as the drive format requires
    gps_profile: GpsProfile = "rtk"  # rtk: 5 Hz, sigma 2 cm; consumer: 1 Hz, sigma 1 m, bias
    gps_rate_hz: float | None = None  # GPS rate (Hz); None = the profile's
    gps_sigma_m: float | None = None  # GPS white noise per axis σ (m); None = the profile's
    gps_bias_m: float | None = None  # std of the slow random-walk bias after 60 s (m)
    # the GPS antenna from the camera centre, [forward, left, up] in the vehicle frame (m):
    # fixes are the antenna's, on the vehicle's pose with its vibration; written to camera.yaml
    # gps_antenna_m when not all 0 (a survey rig measures it; mapping.antenna)
    gps_antenna_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    gps_dropouts: int = 0  # number of GPS outages
    gps_dropout_s: float = 2.0  # length of one GPS outage (s)
    obd_rate_hz: float = 10.0  # OBD speed rate (Hz)
    obd_quant_kmh: float = 1.0  # OBD speed quantisation (km/h), as OBD-II PID 0x0D reports

    # valid values (interval notation; see roadsurf.core.config); a tuple's range holds for
    # each of its values. Upper bounds only where a larger value is a unit mistake
    RANGES: ClassVar[dict[str, str]] = {
        "gps_antenna_m": "[-10, 10]",
        "origin_lat_deg": "[-90, 90]",
        "origin_lon_deg": "[-180, 180]",
        "origin_alt_m": "[-1000, 10000]; roads lie between the Dead Sea and the Andes",
        "route_heading_deg": "[-360, 360]",
        "route_curve_amp_deg": "[0, 180]",
        "route_curve_wavelength_m": "(0, inf)",
        "lateral_wander_m": "[0, inf)",
        "width": "[16, inf)",
        "height": "[16, inf)",
        "fx": "(0, inf)",
        "camera_height_m": "(0, 10]; a camera more than 10 m above the road is a unit mistake",
        "fps": "(0, 1000]",
        "mount_pitch_deg": "[0, 60]; beyond 60 deg the image holds the horizon",
        "mount_roll_deg": "[-15, 15]; a small mounting offset",
        "mount_yaw_deg": "[-15, 15]; a small mounting offset",
        "distortion": "(-inf, inf)",
        "readout_s": "[0, 0.2); and at most one frame period, 1 / fps (check_readout)",
        "speed_mps": "(0, 100]; 100 m/s is 360 km/h",
        "speed_var": "[0, 1]",
        "revisit_after_s": "[0, inf); 0 = one pass",
        "vibration_deg": "[0, 90]",
        "yaw_noise_deg": "[0, 90]",
        "height_noise_m": "[0, 1]",
        "vibration_hz": "[0, inf)",
        "unevenness_m": "[0, 1]",
        "grade": "[-1, 1]; m/m, 1 = 45 deg",
        "cross_slope": "[-1, 1]; m/m, 1 = 45 deg",
        "undulation_m": "[0, 10]",
        "n_potholes": "[0, inf)",
        "pothole_darken": "(0, inf)",
        "pothole_power": "(0, inf)",
        "pothole_size_m": "(0, 10]",
        "pothole_depth_m": "(0, 1]",
        "n_cracks": "[0, inf)",
        "n_ruts": "[0, inf)",
        "n_lane_markings": "[0, inf)",
        "n_shadows": "[0, inf)",
        "n_oil_stains": "[0, inf)",
        "defect_margin_m": "[0, inf)",
        "texel_m": "(0, 1]",
        "texture_cell_m": "(0, inf)",
        "sun_azimuth_deg": "[-360, 360]",
        "sun_elevation_deg": "[0, 90]",
        "ambient": "[0, 1]",
        "cloud_shadow": "[0, 1]",
        "exposure": "(0, inf)",
        "exposure_var": "[0, 1]",
        "vignetting": "[0, 1]",
        "noise_sigma": "[0, 255]; 8-bit DN",
        "shot_noise": "[0, inf)",
        "exposure_time_s": "[0, 1]",
        "jpeg_quality": "[0, 100]",
        "hood_share": "[0, 0.5]; a bonnet over more than half the image leaves little road",
        "supersample": "[1, inf)",
        "render_gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake",
        "raycast_iters": "[1, inf)",
        "truth_gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake",
        "gps_rate_hz": "(0, 1000]",
        "gps_sigma_m": "[0, 100]",
        "gps_bias_m": "[0, 100]",
        "gps_dropouts": "[0, inf)",
        "gps_dropout_s": "[0, inf)",
        "obd_rate_hz": "(0, 1000]",
        "obd_quant_kmh": "[0, inf); 0 = no quantisation",
    }

    @property
    def mounted(self) -> bool:
        """True for a tilted or turned camera (any mount angle), False for the nadir camera."""
        return any((self.mount_pitch_deg, self.mount_roll_deg, self.mount_yaw_deg))

    def vehicle_from_cam(self) -> np.ndarray:
        """(3, 3) R_vehicle_from_cam of the mount (identity for the nadir camera)."""
        return vehicle_from_cam_rotation(
            self.mount_pitch_deg, self.mount_roll_deg, self.mount_yaw_deg
        )

    def check_readout(self) -> None:
        """Raise ConfigError when the readout takes longer than a frame period: a rolling
        shutter reads one frame before it starts the next."""
        if not 0.0 <= self.readout_s < 0.2:
            raise ConfigError(
                f"simulator: readout_s = {self.readout_s!r} s is outside [0, 0.2) (the rolling "
                "shutter's readout time in seconds; 0 = global shutter)."
            )
        if self.readout_s * self.fps > 1.0 + 1e-9:
            raise ConfigError(
                f"simulator: readout_s = {self.readout_s:g} s is longer than one frame period "
                f"(1 / fps = {1.0 / self.fps:.4g} s): a rolling-shutter sensor reads a frame "
                f"before it starts the next. Lower readout_s to <= {1.0 / self.fps:.4g} s or "
                f"fps to <= {1.0 / self.readout_s:.4g} Hz."
            )

    def check_view(self) -> None:
        """Raise ConfigError unless every image-border ray of the camera looks at least
        MIN_DEPRESSION_DEG below the horizon: rays near or above it never meet the road. On a
        climb the vehicle pitches nose-up by the grade (``World.pose``): its rays look higher."""
        climb = math.degrees(math.atan(max(self.grade, 0.0)))
        worst = self._min_depression_deg(self.mount_pitch_deg + climb)
        if worst >= MIN_DEPRESSION_DEG:
            return
        ok = [
            p
            for p in np.arange(60.0, -0.01, -0.5)
            if self._min_depression_deg(p + climb) >= MIN_DEPRESSION_DEG
        ]
        hint = (
            f"mount_pitch_deg <= {ok[0]:g} works with this fx and height"
            if ok
            else "no mount_pitch_deg does with this fx and height"
        )
        raise ConfigError(
            f"simulator: the image's upper border looks only {worst:.1f} deg below the horizon "
            f"(mount_pitch_deg={self.mount_pitch_deg:g} on a grade of {self.grade:g}, "
            f"mount_roll_deg={self.mount_roll_deg:g}, "
            f"mount_yaw_deg={self.mount_yaw_deg:g}, fx={self.fx:g} px, height={self.height} px); "
            f"the renderer needs >= {MIN_DEPRESSION_DEG:g} deg so every ray meets the road. Lower "
            f"mount_pitch_deg, raise fx or lower height ({hint})."
        )

    def _min_depression_deg(self, pitch_deg: float) -> float:
        """Smallest angle below the horizon (deg) of rays through the image border (pixel
        edges, lens distortion undone) for a level vehicle with mount pitch ``pitch_deg``."""
        us = np.linspace(-0.5, self.width - 0.5, 33)
        vs = np.linspace(-0.5, self.height - 0.5, 33)
        u = np.concatenate([us, us, np.full(33, us[0]), np.full(33, us[-1])])
        v = np.concatenate([np.full(33, vs[0]), np.full(33, vs[-1]), vs, vs])
        n = self.camera().normalised_from_raw_px(
            np.column_stack([u, v]), criteria=RENDER_UNDISTORT_CRITERIA
        )
        R = vehicle_from_cam_rotation(pitch_deg, self.mount_roll_deg, self.mount_yaw_deg)
        d = np.column_stack([n, np.ones(len(n))]) @ R.T  # vehicle frame, z down
        return math.degrees(float(np.min(np.arctan2(d[:, 2], np.hypot(d[:, 0], d[:, 1])))))

    def camera(self) -> Camera:
        """The rendered camera, as written to camera.yaml: square pixels (fy = fx), principal
        point at the image centre in the pixel-centre convention (cx = (width - 1) / 2), lens
        distortion ``distortion``; the mount angles only with ``write_mount``; ``readout_s``."""
        mount = (self.mount_pitch_deg, self.mount_roll_deg, self.mount_yaw_deg)
        return Camera(
            width=self.width,
            height=self.height,
            fx=self.fx,
            fy=self.fx,
            cx=(self.width - 1) / 2.0,
            cy=(self.height - 1) / 2.0,
            height_m=self.camera_height_m,
            fps=self.fps,
            dist=tuple(float(k) for k in self.distortion),
            mount_deg=tuple(float(a) for a in mount) if self.write_mount else None,  # type: ignore[arg-type]
            readout_s=float(self.readout_s),
        )
