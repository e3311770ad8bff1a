"""Configuration of the mapping stage (poses, global map, rasters, exports).

Every field gives its unit and, where the dissertation names it, its symbol. Loaded with
``roadsurf.core.config.from_dict`` / ``load_yaml_config`` (unknown keys are rejected).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Literal

from roadsurf.reconstruction.dense.config import DenseHeightConfig

# settings only the dense surface reads (issue 29): with the sparse surface they change nothing,
# so they stay out of the stage keys (runs made before they existed resume); globalmap adds
# them to its key when surface_source is "dense"
DENSE_SURFACE_FIELDS = (
    "surface_source",
    "dense_gsd_m",
    "dense_gsd_px",
    "dense_cloud_spacing_m",
    "dense_min_gsd_m",
    "dense_outlier_sigmas",
    "dense_visible_k",
    "dense_reference",
    "dense_match_image",
    "dense_fill_max_m",
    "dense_sparse_fill",
    "dense_single_view",
    "dense_single_view_relief_m",
    "dense",
)
# settings that change how a result is computed, never the result: a run resumes across them
# (and the dense surface's, see above)
NOT_IN_FINGERPRINT = ("overwrite", "raster_workers", *DENSE_SURFACE_FIELDS)


@dataclass(frozen=True)
class MappingConfig:
    overwrite: bool = False  # recompute even when the stage's artifacts exist (default: resume)
    # ---------------------------------------------------------------- poses (pose graph)
    gps_sigma_m: float = 1.0  # horizontal GPS σ (m) used when the log has no HDOP
    gps_sigma_per_hdop_m: float = 0.5  # σ = hdop × this (m) when HDOP is present (UERE-like)
    gps_sigma_min_m: float = 0.005  # floor on the GPS σ (m), keeps weights finite for RTK logs
    # weigh each fix by the log's own accuracy: its stated σ (gps.csv 'sigma_m', NMEA GST), else
    # by its fix quality when RTK (below), else by HDOP as above. Off by default: the pairs' σ
    # (visual_sigma_trans_rel, 1 % of the baseline) is ~10x the drift measured (0.13 % over
    # 5 m), so with honest 2.5 cm fixes the pose graph follows their noise, and the bundle's
    # time-offset estimate turns significant and wrong: RTK potholes drive, trajectory 9.3 ->
    # 26 mm, in-defect MAE 1.29 -> 1.81 mm (docs/mapping.md, "GPS antenna and accuracy")
    gps_sigma_from_log: bool = False
    # σ (m) of a fix the log marks RTK fixed (NMEA GGA quality 4) or RTK float (5) when it states
    # none of its own (only with gps_sigma_from_log): a fixed solution is good to 1-2 cm +
    # 1 ppm, a float one to decimetres
    gps_sigma_rtk_fixed_m: float = 0.03
    gps_sigma_rtk_float_m: float = 0.3
    gps_vertical_sigma_factor: float = 2.0  # vertical σ = this × horizontal σ (−)
    use_gps_altitude: bool = True  # GPS altitude (when logged) as a weak vertical constraint
    visual_sigma_trans_m: float = 0.003  # σ of a pair's metric translation (m), per axis
    visual_sigma_trans_rel: float = 0.01  # extra σ as a share of the pair's baseline length (−)
    visual_sigma_rot_deg: float = 0.1  # σ of a pair's relative rotation (degrees), per axis
    heading_sigma_deg: float = 5.0  # σ of the eq. 6.1 heading between successive fixes (degrees)
    heading_min_baseline_m: float = 0.5  # fixes closer than this give no heading (m)
    tilt_sigma_deg: float = 3.0  # σ of the road normal vs world up (road grade/cross-fall) (deg)
    # the road's grade from the GPS heights (mapping.grade): a Gaussian window of this length
    # along the track (m); the tilt prior holds the mount's up axis on the road's normal, world
    # up tipped by the grade (a 1 % grade moved a 25° camera's map 12 mm); 0 = a level road
    grade_window_m: float = 10.0
    # σ_γ: prior spread of the road's grade (%; mapping.grade shrinks the fitted grade towards
    # a level road against it and widens the window until the fit's error is below half of it).
    # Road design keeps most road length within ±2-4 % (arterial maxima 4-6 %, local streets up
    # to 8-12 % in hills): 2 % puts 95 % of grades within ±4 %. Not the tilt prior's σ, which
    # also holds cross-fall and vibration
    grade_sigma_pct: float = 2.0
    # which axis the tilt prior holds vertical: the mount's up axis (camera.yaml's mount, or
    # the one estimated from the drive; the optical axis of a nadir camera) or the road normal
    # of each pair's plane fit (assumes no cross-fall). Camera roll is not observable from GPS
    # on a straight drive; an error of θ shifts the map by camera height × tan θ (2 %
    # cross-fall, 1.1 m: 22 mm)
    tilt_prior_axis: Literal["mount", "road_normal"] = "mount"
    # φ: the road's cross-fall the vehicle rolls with (%, + = the road falls to the right of
    # travel), which tips the tilt prior's axis as the grade does. Roll is not observable from
    # a camera and GPS (no IMU): 0 places the map for a level vehicle, and a real cross-fall c
    # then moves it (camera height + the GPS antenna's height above the camera) × c sideways
    # and drops c from its heights across the road. Set the
    # design value where it is known (a crowned road driven in its outer lane: about +2 where
    # traffic keeps right, −2 where it keeps left)
    cross_fall_pct: float = 0.0
    # estimate the camera's mount (pitch, roll, yaw) from the pairs' road normals and
    # directions of travel when camera.yaml does not give it (mapping.mount); off: nadir
    estimate_mount: bool = True
    # apply an estimated mount pitch only beyond this (deg): below it a forward mount and the
    # drive's mean grade look the same (8.7 % grade = 5°), and the camera is taken as nadir
    mount_min_pitch_deg: float = 5.0
    # warn when camera.yaml's mount and the drive's estimate differ by more than this (deg)
    mount_disagree_deg: float = 3.0
    gps_bridge_s: float = 2.0  # fixes this close before and after a failed pair bridge it (s)
    # fixes up to this long before the first frame or after the last are used too, through the
    # end frames extrapolated at constant velocity; their σ grows by ½·a·Δt² (a =
    # gap_accel_sigma_mps2, Δt = time outside the frames). A short drive's heading rests on its
    # few fixes: with 1 Hz GPS, one dropout and one bad fix, the ends are what let the outlier
    # test see it (s; 0 = only fixes within half a frame interval of the frames)
    gps_extrapolate_s: float = 1.5
    gap_sigma_m: float = 1.0  # σ of the constant-velocity guess across a failed pair (m)
    gap_sigma_rot_deg: float = 10.0  # σ of its rotation (deg)
    # σ of the vehicle's acceleration (m/s²) in the constant-velocity prior on the positions of
    # frames next to a visual gap (a failed pair, or frames a fused run did not reconstruct):
    # without it such a frame is held only by GPS (slower than the camera), OBD speed (a norm,
    # blind across the track) and the 1 m gap guess, and the solver crawls (0 = off)
    gap_accel_sigma_mps2: float = 3.0
    adapt_sigmas: bool = True  # rescale GPS/visual σ from the fit's own residuals (robust MAD)
    obd_sigma_mps: float = 0.2  # σ of OBD speed (m/s) for the optional speed constraint
    use_obd: bool = True  # add OBD speed constraints when obd.csv exists
    robust_loss: Literal["soft_l1", "huber", "cauchy", "arctan", "linear"] = "cauchy"
    robust_scale: float = 3.0  # residual (in σ units) where the robust loss starts to bend (−)
    gps_outlier_sigmas: float = 5.0  # a fix with |residual| > this × σ after fusion is an outlier
    max_nfev: int = 60  # least-squares iteration cap (function evaluations)
    # ---------------------------------------------------------------- bundle adjustment (issue 30)
    # refine the pose graph's poses by bundle adjustment over feature tracks (mapping.bundle):
    # reprojection, road-plane and camera-height priors, the pairs' motions, GPS with an
    # estimated time offset; False = the pose graph alone
    bundle_adjust: bool = True
    bundle_window_frames: int = 30  # frames per sliding window (count)
    bundle_overlap_frames: int = 10  # frames a window shares with the next one (count)
    bundle_pixel_sigma_px: float = 0.5  # σ of a track's pixel position (px)
    # σ of the road's departure from one plane over a frame's footprint (m; undulation, ruts,
    # cross-fall change: several mm over 2-8 m). The departure is smooth, so a frame's N road
    # points share it: each point's term weighs 1/√N (together one plane's worth, not N
    # independent 1 cm measurements, which bent the point cloud and with it the cameras' tilt:
    # potholes, 5-frame rotation error 0.15° against the pose graph's 0.04°); the plane only
    # carries the camera height (scale). A σ below the real relief forces it into the poses
    bundle_relief_sigma_m: float = 0.01
    bundle_height_sigma_m: float = 0.005  # σ of the camera height above that plane, h (m)
    bundle_prior_sigma_m: float = 0.3  # σ of the pull to the pose graph's centres (m; gauge)
    # the GPS - camera time offset (GPS latency) is searched within ± this (s; 0 = not estimated)
    bundle_max_time_offset_s: float = 0.5
    bundle_max_two_view: int = 50  # two-view tracks kept per frame (count; 3+-view: all)
    # a track whose consecutive pairs disagree by more, after their smooth (affine on the
    # road) disagreement is removed, is dropped (m)
    bundle_track_tol_m: float = 0.02
    bundle_max_nfev: int = 20  # least-squares evaluations per window (count)
    # refine the focal length (one scale on fx and fy for the drive; real calibrations are off by
    # a fraction of a percent to a few percent): every window estimates it with a prior of
    # bundle_focal_sigma around the calibration, the windows' median is held in a second pass
    # (twice the bundle's time). With it on, the later stages (map, dense surface, mosaic,
    # detection) use the refined focal, and the pairs re-derived with it (mapping.bundle_camera)
    bundle_refine_focal: bool = False
    bundle_focal_sigma: float = 0.05  # prior σ of the focal scale around the calibration (−)
    # refine the radial distortion k1 (dist[0]; one value for the drive, as the focal length: a
    # per-window estimate with a prior of bundle_k1_sigma around camera.yaml's k1, the windows'
    # median held in a second pass). With it on, the later stages (map, dense surface,
    # detection) use the refined k1, and the pairs re-derived with it (mapping.bundle_camera).
    # k1 is the coefficient of r² with r the normalised radius (a point's distance from the
    # principal point in units of the focal length)
    bundle_refine_k1: bool = False
    # prior σ of k1 around camera.yaml's (−, per unit r²): a weak prior, wider than the spread
    # of a real lens's k1 against a nominal 0 (consumer lenses |k1| ≲ 0.3)
    bundle_k1_sigma: float = 0.1
    # the pose graph's placement (all GPS fixes at once) is kept at scales beyond this length of
    # path; the bundle's own placement rests on one window's fixes (m; 0 = the bundle's own)
    bundle_placement_length_m: float = 25.0
    # loop closure (revisits; needs a matcher, mapping.loops): frames at least this far apart
    # in time (s) whose placed camera centres are within the gate (m: a few GPS σ of two passes'
    # placement plus the footprint) are matched; 0 = no loop closure
    bundle_loop_gate_m: float = 3.0
    bundle_loop_min_gap_s: float = 10.0
    # ---------------------------------------------------------------- global map
    # warn when consecutive frames' road footprints overlap by less than this share (0-1): below
    # half, the pairs' two-view parts no longer touch and the map has gaps between them
    min_frame_overlap: float = 0.5
    voxel_m: float = 0.004  # voxel edge for fusing points seen in several pairs (m)
    max_point_depth_m: float = 5.0  # drop points further than this from camera a (m)
    local_fit_window_m: float = 1.5  # side of the window for the local road-surface fit (m)
    local_fit_cell_m: float = 0.25  # cell size of the local fit's anchor grid (m)
    local_fit_inlier_m: float = 0.008  # points further than this from the fit are not road (m)
    # side of a coarse window fitted first (m; 0 or <= local_fit_window_m = off): a pothole
    # wider than the local window fills some windows, whose fits would follow its floor; the
    # coarse fit spans it and the local fit starts from the points near the coarse road
    local_fit_bridge_m: float = 4.0
    align_patches: bool = True  # remove per-pair height offset/tilt against the fused surface
    # ---------------------------------------------------------------- rasters / exports
    # ground sampling distance of surface.tif / mosaic.tif with the sparse surface (m); the
    # dense surface (the default) uses dense_gsd_m, and only a finer gsd_m than its own cell
    # lowers it (a coarser one warns and names dense_gsd_m)
    gsd_m: float = 0.005
    tile_px: int = 1024  # raster tile side (px); tiles exist only where the corridor passes
    tiled_vrt_min_tiles: int = 2  # write per-tile files + VRT index when the grid has >= this
    mosaic_border_px: int = 0  # image border ignored when projecting frames (px); edge pixels
    # are sampled with edge replication, and the feathering already down-weights them
    feather_px: int = 40  # feathering ramp width at image edges for mosaic blending (px)
    max_raster_px: int = 20_000_000_000  # bounding grid above this (px): tiles + VRT only
    preview_max_px: int = 2000  # longest side of the PNG previews (px)
    raster_workers: int = 2  # threads computing raster tiles (count); tiles are written in order
    surface_max_edge_m: float = (
        0.10  # never interpolate the surface across a gap wider than this (m)
    )
    surface_smooth_m: float = 0.01  # σ of the masked Gaussian that averages point noise (m)
    surface_smooth_flat_m: float = (
        0.03  # σ of the stronger smoothing used where relief is noise (m)
    )
    surface_detail_sigmas: float = 2.0  # fine/coarse difference (× point noise MAD) kept as relief
    surface_smooth_defect_m: float = 0.005  # σ of the light smoothing kept in relief (m)
    surface_interp_step_px: int = (
        2  # interpolate/smooth the surface on a grid this much coarser (px)
    )
    surface_edge_factor: float = 4.0  # ... nor wider than this × the median point spacing (−)
    # extend the surface from its measured points by at most this distance (m), only where BOTH
    # frames of an ok pair saw the road (projected with the fused poses), and only in the strip
    # of this width along the border of that two-view part (matches stop short of the image
    # borders) or in whole holes no wider than twice this (larger holes, e.g. unmatched pothole
    # floors, stay holes). The filled height is the local road fit plus a Gaussian-weighted mean
    # of the nearby measured residuals (σ = half this), like GDAL fillnodata with a max distance:
    # it continues the measured surface, never creates a depression; 0 = off. Half of
    # surface_max_edge_m: a gap the interpolation would bridge with points on both sides
    surface_fill_max_m: float = 0.05
    # ... and only where the measured surface around is road: its residual within
    # max(surface_detail_sigmas × point noise, this) (m); deeper relief (a defect running off
    # the measured part) is not extrapolated. The floor keeps road texture (mm) from blocking
    # the fill when the points are nearly noise-free
    surface_fill_relief_min_m: float = 0.002
    colour_from_images: bool = True  # sample point colours from image a at px_a
    # ---------------------------------------------------------------- dense surface (issue 29)
    # where surface.tif comes from: "sparse" = the fused feature points, interpolated; "dense" =
    # every pixel of each ok pair's overlap matched (reconstruction.dense) and fused per cell
    # (mapping.dense_fuse), with the sparse surface where the matching leaves a hole; surface
    # and mosaic then share the dense GSD. Dense is the default: better flat and in-defect MAE
    # and coverage on every measured drive (docs/mapping.md)
    surface_source: Literal["sparse", "dense"] = "dense"
    dense_gsd_m: float = 0.0  # raster GSD with the dense surface (m); 0 = dense_gsd_px x the
    # images' ground sampling at the matching scale (1.8 mm/px for 640 x 480, f = 600 px, 1.1 m)
    # a cell of this many matched pixels (px): the heights are window means (dense.window_px =
    # 5 px), so 2 px cells sample them at about their Nyquist rate; on the potholes drive 1 and
    # 2 px gave the same flat and in-defect MAE, and 2 px cost a quarter of the cells. Never
    # coarser than gsd_m unless one pixel is
    dense_gsd_px: float = 2.0
    # cloud.ply with the dense surface: one point per measured cell, every k-th cell along rows
    # and columns so that points are at most this far apart (m; 0 = every cell). 5 mm: at least
    # 40,000 points/m² (issue 29); with 2 px cells of 1.8 mm pixels every cell is kept
    dense_cloud_spacing_m: float = 0.005
    dense_min_gsd_m: float = 0.001  # ... never finer than this (m): bounds the raster's size
    # a pair's sample further than this x its σ (+ 0.2 mm) from the cell's weighted median is
    # left out of the cell's mean (−)
    dense_outlier_sigmas: float = 3.0
    # a pair's sample of a cell counts only where the point its pixel sees lies within this x
    # max(the pixel's ground footprint, the cell) of the cell's centre (−; 0 = off; 2: about
    # the default 5 px window's half-width): a tilted camera cannot see a pothole's near wall,
    # whose cells otherwise took the floor's height (benchmarks/stereo_pair.py)
    dense_visible_k: float = 2.0
    # what the dense heights are relative to: each pair's own robust plane (its road, ~1 m), or
    # the local road surface fitted to the sparse points with each pair's offset and tilt to it
    # removed
    dense_reference: Literal["pair_plane", "local_surface"] = "pair_plane"
    # the image of a pair whose pixels the dense heights are measured on: "nearer" = the one
    # whose camera sees the pair's common road from nearer (finer ground sampling; image b of
    # a camera tilted forward, image a of a nadir one), "a" = always image a
    # (mapping/dense_refimage.py)
    dense_match_image: Literal["a", "nearer"] = "nearer"
    # extend the dense surface by at most this (m) inside the part both frames of an ok pair saw,
    # where the relief is road (surface_fill_relief_min_m): the matching windows stop a few
    # pixels short of the images' borders; 0 = off
    dense_fill_max_m: float = 0.01
    # cells the dense matching left empty (a real pothole's dark, wet or textureless floor fails
    # its masks) take the sparse surface's value where the fused feature points cover them:
    # on the spd2 photographs every pothole floor was a hole in the dense surface, so the
    # defects were rings
    dense_sparse_fill: bool = True
    # cells of the imaged corridor that no ok pair saw twice (a tilted camera's far-field
    # corners: a wide trapezoid top passes out of view before the next shot; 15 % of the
    # corridor at 25-45° forward, measured): "road" = the local road model's height (residual
    # 0), with count 0 in surface_nobs.tif and σ the road's per-point spread (a modelled, not a
    # measured, height; left out of cloud.ply and of the measured share in report.json);
    # "empty" = left NaN. A single view has no parallax, so nothing better can be measured there
    dense_single_view: Literal["road", "empty"] = "road"
    # ... except those whose nearest known cell within this distance (m) is relief (beyond
    # the fill relief limit): unknown, NaN. Below 50 % frame overlap (7.5 m/s at 15 fps, 1.1 m,
    # f = 600 px: 43 %) a strip between two pairs' parts is seen once; the road model across a
    # pothole split it into a defect per pair (precision 0.88 -> 0.58), its depth continued
    # joined two. 0.25 m covers strips up to 0.5 m (0 = the road model everywhere)
    dense_single_view_relief_m: float = 0.25
    # the matching; the heights smoothed edge-preserving within about the matching window's own
    # extent (smooth_px = 1.5 px ~ the 5 px window's σ, 5/√12; range 3 mm: about 2 x the
    # cells' noise σ): see DenseHeightConfig.smooth_px
    dense: DenseHeightConfig = field(default_factory=lambda: DenseHeightConfig(smooth_px=1.5))

    # valid values (interval notation; see roadsurf.core.config). Upper bounds only where a
    # larger value is a unit mistake
    @property
    def cross_fall_rad(self) -> float:
        """φ = atan(cross_fall_pct / 100) (rad)."""
        return math.atan(self.cross_fall_pct / 100.0)

    RANGES: ClassVar[dict[str, str]] = {
        "gps_sigma_m": "(0, 100]; a GPS σ above 100 m is a unit mistake",
        "gps_sigma_per_hdop_m": "(0, 100]",
        "gps_sigma_min_m": "(0, 100]; a floor of 0 gives RTK fixes infinite weight",
        "gps_sigma_rtk_fixed_m": "(0, 100]",
        "gps_sigma_rtk_float_m": "(0, 100]",
        "gps_vertical_sigma_factor": "(0, inf)",
        "visual_sigma_trans_m": "(0, inf)",
        "visual_sigma_trans_rel": "[0, 1]",
        "visual_sigma_rot_deg": "(0, 180]",
        "heading_sigma_deg": "(0, 180]",
        "heading_min_baseline_m": "[0, inf)",
        "tilt_sigma_deg": "(0, 90]",
        "grade_window_m": "[0, inf); 0 = a level road",
        "grade_sigma_pct": "(0, 100]; 100 % = 45 deg",
        "cross_fall_pct": "[-20, 20]; % (a superelevated curve reaches 8-12 %)",
        "mount_disagree_deg": "(0, 90]",
        "mount_min_pitch_deg": "[0, 90]",
        "gps_bridge_s": "[0, inf)",
        "gps_extrapolate_s": "[0, inf)",
        "gap_sigma_m": "(0, inf)",
        "gap_sigma_rot_deg": "(0, 180]",
        "gap_accel_sigma_mps2": "[0, inf); 0 = off",
        "obd_sigma_mps": "(0, inf)",
        "robust_scale": "(0, inf)",
        "gps_outlier_sigmas": "(0, inf)",
        "max_nfev": "[1, inf)",
        "bundle_window_frames": "[4, inf)",
        "bundle_overlap_frames": "[0, inf); below bundle_window_frames - 2",
        "bundle_pixel_sigma_px": "(0, inf)",
        "bundle_relief_sigma_m": "(0, 1]; a relief σ above 1 m is a unit mistake",
        "bundle_height_sigma_m": "(0, 1]",
        "bundle_prior_sigma_m": "(0, inf)",
        "bundle_max_time_offset_s": "[0, 10]; 0 = not estimated",
        "bundle_max_two_view": "[0, inf)",
        "bundle_track_tol_m": "(0, 1]",
        "bundle_max_nfev": "[1, inf)",
        "bundle_focal_sigma": "(0, 1]",
        "bundle_k1_sigma": "(0, 1]",
        "bundle_placement_length_m": "[0, inf)",
        "bundle_loop_gate_m": "[0, inf)",
        "bundle_loop_min_gap_s": "(0, inf)",
        "min_frame_overlap": "[0, 1]",
        "dense_single_view_relief_m": "[0, inf); 0 = the road model everywhere",
        "voxel_m": "[0, 1]; 0 = no fusion; a voxel above 1 m is a unit mistake (mm typed as m?)",
        "max_point_depth_m": "(0, inf)",
        "local_fit_window_m": "(0, inf)",
        "local_fit_cell_m": "(0, inf)",
        "local_fit_inlier_m": "(0, inf)",
        "local_fit_bridge_m": "[0, inf); 0 = off",
        "gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake (cm typed as m?)",
        "tile_px": "[16, 65536]; smaller tiles would be millions of files",
        "tiled_vrt_min_tiles": "[0, inf)",
        "mosaic_border_px": "[0, inf)",
        "feather_px": "[0, inf)",
        "max_raster_px": "[1, inf)",
        "preview_max_px": "[16, inf); a PNG preview needs some pixels",
        "raster_workers": "[1, inf)",
        "surface_max_edge_m": "(0, inf)",
        "surface_smooth_m": "[0, inf)",
        "surface_smooth_flat_m": "[0, inf)",
        "surface_detail_sigmas": "[0, inf)",
        "surface_smooth_defect_m": "[0, inf)",
        "surface_interp_step_px": "[1, inf)",
        "surface_edge_factor": "(0, inf)",
        "surface_fill_max_m": "[0, inf); 0 = off",
        "surface_fill_relief_min_m": "[0, inf)",
        "surface_source": "{sparse, dense}",
        "dense_gsd_m": "[0, 1]; 0 = from the images; a cell above 1 m is a unit mistake",
        "dense_gsd_px": "[0.5, 16]",
        "dense_cloud_spacing_m": "[0, 1]",
        "dense_min_gsd_m": "(0, 1]",
        "dense_outlier_sigmas": "(0, inf)",
        "dense_visible_k": "[0, inf); 0 = off",
        "dense_reference": "{pair_plane, local_surface}",
        "dense_match_image": "{a, nearer}",
        "dense_fill_max_m": "[0, inf); 0 = off",
    }
