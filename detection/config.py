"""Configuration of the detection stage (dissertation Ch. 4 and §5.4). Frozen dataclasses.

Symbols follow the dissertation: T_d (depth threshold, eq. 4.8), m (minimum road share, eq. 4.10),
T_b (binarisation threshold, Fig. 4.3), W (erosion/dilation window, Fig. 4.3), w (mean-shift
window, eq. 5.11-5.12). Depth thresholds are floors: the stage raises them to a multiple of the
measured noise of the residual surface (robust MAD of the flat road), so one setting works on
renders and real roads with different noise.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar, Literal

BinariseMode = Literal["adaptive", "fixed"]
FrameLabelMode = Literal["map", "pair"]
DEFECT_TYPES: tuple[str, ...] = ("pothole", "crack", "rut")
SEVERITIES: tuple[str, ...] = ("low", "medium", "high")


@dataclass(frozen=True)
class PlaneFitConfig:
    """Recursive plane fit per pair (eq. 4.8-4.10)."""

    depth_threshold_m: float = 0.008  # T_d floor: candidate when d_i < 0 and |d_i| >= T_d (m)
    noise_k: float = 4.0  # T_d = max(T_d floor, noise_k * σ_noise), σ from MAD of d_i (unitless)
    min_road_share: float = 0.7  # m: refit while T_n = |X^rn| / |X| > m (0-1)
    max_iterations: int = 10  # cap on refits (count)
    min_points: int = 30  # a pair with fewer points is not segmented (count)
    max_depth_m: float = 0.25  # points further below the plane are mismatches, not defects (m)

    # valid values (interval notation; see roadsurf.core.config)
    ORDER: ClassVar[tuple[tuple[str, str], ...]] = (("depth_threshold_m", "max_depth_m"),)
    RANGES: ClassVar[dict[str, str]] = {
        "depth_threshold_m": "[0, 1]; a T_d above 1 m is a unit mistake (mm typed as m?)",
        "noise_k": "[0, inf)",
        "min_road_share": "[0, 1]",
        "max_iterations": "[1, inf)",
        "min_points": "[3, inf); a plane needs 3 points",
        "max_depth_m": "(0, 10]; a defect deeper than 10 m is a unit mistake",
    }


@dataclass(frozen=True)
class RefineConfig:
    """2D + 3D refinement (Fig. 4.3 CORRECT_DEFECTS)."""

    # run the 2D gate with the map's frame labels too (frame_label "pair", the dissertation's
    # per-pair decision, always runs it). Off by default since issue 29: on the dense default
    # it changed no output on six simulated drives and the spd2 photographs (docs/detection.md,
    # "Which 2D heuristics the dense default still needs"); True for the comparison (bool)
    enabled: bool = False
    binarise: BinariseMode = "adaptive"  # T_b policy: adaptive (per image, local road) | fixed
    fixed_threshold: int = 90  # T_b for `fixed`: dark = grey < T_b (grey level 0-255)
    adaptive_window_frac: float = 0.25  # local road brightness window, share of image width (0-1)
    adaptive_dark_k: float = 1.5  # adaptive: dark = grey < local median - k * local MAD (unitless)
    adaptive_min_drop: float = 0.06  # adaptive: and at least this share darker than local (0-1)
    adaptive_blur_frac: float = 0.02  # adaptive: compare grey box-averaged over this x width (-)
    window_px: int = 5  # W: erosion then dilation window W x W (px)
    grow_depth_frac: float = 0.5  # grow: a point joins when inside the region and d_i <= -frac*T_d
    strong_factor: float = 2.5  # candidates deeper than strong_factor * T_d need no 2D support
    max_iterations: int = 10  # grow until the set is stable, at most this many rounds (count)

    RANGES: ClassVar[dict[str, str]] = {
        "fixed_threshold": "[0, 255]; an 8-bit grey level",
        "adaptive_window_frac": "(0, 1]",
        "adaptive_dark_k": "[0, inf)",
        "adaptive_min_drop": "[0, 1]",
        "adaptive_blur_frac": "[0, 1]",
        "window_px": "[1, inf)",
        "grow_depth_frac": "[0, 1]",
        "strong_factor": "[0, inf)",
        "max_iterations": "[1, inf)",
    }


@dataclass(frozen=True)
class CrackConfig:
    """Thin dark linear features confirmed by 3D points just below the road (cracks)."""

    enabled: bool = True  # run the crack detector (needs the images)
    tophat_m: float = 0.025  # black top-hat disc: wider than a crack, narrower than a pothole (m)
    # Oriented line filter on the top-hat: segments much longer than texture grains (gravel
    # pores: a few mm) and short enough to follow a curved crack (sagitta L² / 8R ≈ 1 mm at
    # R = 0.2 m).
    line_m: float = 0.04  # segment length (m)
    # ... and a second, longer segment (0 = off), thresholded on its own: on busy textures
    # (brick, coarse chip seal) 4 cm segments of texture answer almost like a crack, while a
    # crack's straight stretches keep their contrast over 12 cm and the texture's do not (m).
    line_long_m: float = 0.12
    long_contrast_k: float = 4.5  # ... its threshold: median + k * 1.4826 MAD (-)
    line_long_gsd_m: float = 0.004  # ... run at pixels <= this (m; 0.008 is 2x faster, misses
    # the thinnest cracks)
    # ... run at the coarsest integer downsampling with pixels <= this: a 3-8 mm crack stays
    # about a pixel wide (area averaging keeps its darkness) and the kernels stay small (m).
    line_gsd_m: float = 0.004
    contrast_k: float = 3.0  # line response > median + k * 1.4826 MAD of the image's (-)
    # ... and the line at least this much darker than its surroundings, as a share of their
    # brightness: a crack is a shadowed void, tens of % darker at its centre (simulator: up to
    # 60 %); shading ripples, JPEG and paint wear along a line stay below (0-1).
    min_contrast: float = 0.03
    min_length_m: float = 0.08  # a crack piece is at least this long (m)
    max_width_m: float = 0.025  # ... and at most this wide on average (m; FHWA high > 19 mm)
    min_elongation: float = 8.0  # length / mean width at least (unitless)
    # 3D points within max(near_px, half the crack's width) of its centre line test it (px)
    near_px: float = 1.0
    # 3D test pooled over all pairs whose pieces link up on the map:
    min_points: int = 5  # at least this many 3D points on the crack (count)
    # A piece's sparse depths read against the local road: a plane through the pair's road
    # points within this ground distance of its centre line (m; 0 = the pair's plane, the
    # default: on the tilted drives the two agree within 0.6 mm and it found no crack more;
    # 0.1 m holds ~50-100 road points around a 0.5 m crack, docs/detection.md) ...
    local_road_m: float = 0.0
    local_road_min_points: int = 12  # ... when at least this many (count; else the pair's plane)
    # ... and farther than this from it in the image: half the reconstruction's LK window
    # (21 px), so the crack's edge took no part in their match (px)
    local_road_gap_px: float = 11.0
    # one point's (one dense track's) σ is at least the crack's points' own standard deviation
    # (3 or more): a window on a line slides along it, so they may scatter more than the road
    # (off: measured 1.5-1.8 x the road's on the tilted drives; costs recall, docs) (-)
    own_scatter: bool = False
    min_below_share: float = 0.6  # share of them below the road plane (0-1)
    z_k: float = 3.0  # Σ depth / sqrt(Σ n σ²) >= z_k, σ: each pair's point noise (unitless)
    # Dense depth across the crack (LK tracks of its centre line against a side road band):
    dense: bool = True  # measure it when the pair's image b is at hand
    dense_window_px: int = 7  # LK window (px): the crack and its two edges, little else
    # parallax across the crack below this share of the full parallax (|sin| of the angle
    # between crack and epipolar direction < 0.25, i.e. within ~15°): LK's aperture hides it (-)
    dense_min_across: float = 0.25
    dense_max_depth_m: float = 0.05  # |depth| beyond this: a failed track, not a crack floor (m)
    # ... read by a groove model fitted to the cross-section profiles in both images
    # (``crackgroove``) instead of the LK tracks: a window's shift sees 0.15-0.4 of a groove's
    # depth (its rims do not move) and, on busy texture, mostly the texture's (road-level)
    # shift; the model separates the groove's displacement from the road's. LK where the model
    # measures nothing
    groove: bool = True
    # profiles (one per centre-line pixel) pooled into blocks of this many px along the crack,
    # taken as independent: a profile reads bilinear samples and a 3 px gradient, so its
    # neighbours within ~2 px share pixels; blocks 4x that (px)
    groove_block_px: float = 8.0
    groove_min_blocks: int = 5  # at least this many blocks (count; 7 cm of crack at 1.8 mm/px)
    groove_iterations: int = 4  # Gauss-Newton steps per profile (count; 1 px moves converge in 3)
    max_samples: int = 150  # samples per crack piece mapped onto the road (count)
    link_m: float = 0.08  # samples closer than this on the map are one crack (m)
    join_m: float = 0.2  # confirmed cracks closer than this are joined into one (m)
    # Width and depth across the centre line on the surface raster (``crackraster``):
    raster: bool = True  # measure each crack on RUN/surface.tif when there is one
    raster_step_m: float = 0.005  # a profile across the crack every this much along it (m)
    # road read beyond the crack's dip on each side of a profile, at least 2 footprints (m)
    raster_road_m: float = 0.02
    # smoothing footprint of a raster whose surface.tif has no DENSE_FOOTPRINT_M tag (mapping
    # writes the dense window's ground footprint there), in cells: the dense matcher's window
    # (5 px) over the cell (dense_gsd_px = 2 px) = 2.5; the dip is at most half the width +
    # this wide (cells)
    raster_footprint_cells: float = 2.5
    raster_min_profiles: int = 5  # at least this many profiles with road on both sides (count)
    # the cross-section must be this many standard errors above 0, and a resolved dip's depth
    # this many σ of the raster (unitless)
    raster_z_k: float = 3.0
    # resolved: the dip is at least this many footprints wide at half depth; then the raster
    # gives width and depth, else only the cross-section (unitless)
    raster_resolved_k: float = 2.0
    # A candidate the pooled 3D test leaves unconfirmed is confirmed on the raster when its
    # cross-section is below the road beyond its noise (``crackraster.raster_crack_evidence``;
    # z at Student's t, one-sided, at the level of raster_z_k σ). On the simulated drives the
    # 9 mm dense footprint keeps too little of a 4-7 mm crack for it to confirm one the pooled
    # test misses (tilted 25° D008 z 1.9, 45° D007 2.1, highway D006 1.7; thresholds ~3.2)
    raster_confirm: bool = True
    # profiles are pooled into blocks this many footprints long along the crack, whose means
    # are taken as independent: the dense raster's noise decorrelates within ~2 footprints (its
    # window and smoothing; autocorrelation 0.89 / 0.38 / ~0 at 1 / 3 / 5 cells of 3.7 mm on
    # the nadir tilted drive), the blocks are twice that. Random crack-free lines on five
    # simulated rasters reached the threshold 5 times in 1,558 (0.32 %; nominal 0.135 %; 6 and
    # 8 footprints: 4 / 1,537 and 5 / 1,476) (unitless)
    raster_block_footprints: float = 4.0
    raster_min_blocks: int = 5  # at least this many blocks (count; ~18 cm of crack at 9 mm)
    # A candidate both 3D tests leave unconfirmed where they are blind (``crackimage``: it runs
    # within the aperture angle of the epipolar direction, ``dense_min_across``, or its pairs'
    # depth readings disagree beyond their errors, Cochran's Q at the level of ``z_k``) is kept
    # on 2D evidence, its depth not measured (NaN, ``measured_on: image``)
    image_confirm: bool = True
    image_disagree: bool = True  # ... count disagreeing readings as blind (else the aperture only)
    # ... when the dark line was extracted in at least this many pairs at the same place (within
    # link_m on the map; count: a filter artefact of one image, noise or a moving shadow, does
    # not repeat there; 2 admitted a brick joint along the travel at the edge of the coverage
    # (2 of 2 pairs, brick25), which a static road-level line is, docs) ...
    image_min_pairs: int = 3
    # ... and in at least this share of the pairs whose image a covers it (0-1)
    image_min_share: float = 0.5

    ORDER: ClassVar[tuple[tuple[str, str], ...]] = (("line_m", "line_long_m"),)
    RANGES: ClassVar[dict[str, str]] = {
        "tophat_m": "(0, 1]; a top-hat disc above 1 m is a unit mistake",
        "line_m": "(0, inf)",
        "line_long_m": "[0, inf); 0 = off",
        "long_contrast_k": "[0, inf)",
        "line_long_gsd_m": "(0, 1]; a pixel above 1 m is a unit mistake",
        "line_gsd_m": "(0, 1]; a pixel above 1 m is a unit mistake",
        "contrast_k": "[0, inf)",
        "min_contrast": "[0, 1]",
        "min_length_m": "[0, inf)",
        "max_width_m": "(0, inf)",
        "min_elongation": "[1, inf); length / width",
        "near_px": "[0, inf)",
        "min_points": "[1, inf)",
        "local_road_m": "[0, inf); 0 = the pair's plane",
        "local_road_min_points": "[3, inf); a plane needs 3 points",
        "local_road_gap_px": "[0, inf)",
        "min_below_share": "[0, 1]",
        "z_k": "[0, inf)",
        "dense_window_px": "[3, inf); OpenCV's Lucas-Kanade needs a window wider than 2 px",
        "dense_min_across": "[0, 1]",
        "dense_max_depth_m": "(0, 1]; a crack deeper than 1 m is a unit mistake",
        "groove_block_px": "(0, inf)",
        "groove_min_blocks": "[2, inf); a spread needs 2 blocks",
        "groove_iterations": "[1, inf)",
        "max_samples": "[1, inf)",
        "link_m": "[0, inf)",
        "join_m": "[0, inf)",
        "raster_step_m": "(0, 1]; a profile step above 1 m is a unit mistake",
        "raster_road_m": "(0, 1]",
        "raster_footprint_cells": "[0, inf)",
        "raster_min_profiles": "[1, inf)",
        "raster_z_k": "[0, inf)",
        "raster_resolved_k": "[0, inf)",
        "raster_block_footprints": "(0, inf)",
        "raster_min_blocks": "[2, inf); a spread needs 2 blocks",
        "image_min_pairs": "[2, inf); one pair's line is no consistency",
        "image_min_share": "[0, 1]",
    }


@dataclass(frozen=True)
class DenseConfig:
    """Dense measurement inside each candidate defect, per pair (LK tracks, see detection/dense.py
    and densepair.py)."""

    enabled: bool = True  # measure depths, area and volume from dense tracks (needs the images)
    step_px: float = 2.0  # track every step_px-th pixel of image a inside the defect (px)
    window_px: int = 7  # Lucas-Kanade window (px): small, so it does not smooth the bottom
    edge_m: float = 0.03  # the raster outline grown by this much is measured (m)
    ring_m: float = 0.08  # road ring beyond that which levels the depths (m)
    rim_noise_k: float = 2.0  # a dense point is in the defect when deeper than k σ_dense (-)
    min_coverage: float = 0.6  # dense depths must cover this share of the outline (0-1)
    max_noise_k: float = 3.0  # a pair's dense road σ above k x the sparse σ: its tracks failed (-)
    # wrong-track check window (m): a track is dropped where < 20 % of the window's tracks are
    # valid (an island), or 6 σ, 5 mm and 25 % deeper than the window's 75th percentile (a
    # patch narrower than a quarter of it)
    patch_window_m: float = 0.04
    # area at depth 0 (the rim) extrapolated from the areas deeper than 1x and 2x the rim threshold
    area_extrapolate: bool = True
    area: bool = True  # area from the dense points (False: cells of the raster outline)

    RANGES: ClassVar[dict[str, str]] = {
        "step_px": "(0, inf)",
        "window_px": "[3, inf); OpenCV's Lucas-Kanade needs a window wider than 2 px",
        "edge_m": "[0, inf)",
        "ring_m": "(0, inf)",
        "rim_noise_k": "[0, inf)",
        "min_coverage": "[0, 1]",
        "max_noise_k": "(0, inf)",
        "patch_window_m": "(0, inf)",
    }


@dataclass(frozen=True)
class SeverityConfig:
    """Severity bands (ASTM D6433 pothole table; FHWA Distress Identification Manual depths)."""

    depth_low_m: float = 0.025  # depth band edge low/medium (m), ASTM D6433 & FHWA DIM: 25 mm
    depth_high_m: float = 0.050  # depth band edge medium/high (m): 50 mm
    diameter_small_m: float = 0.200  # ASTM D6433 diameter edge 100-200 / 200-450 mm (m)
    diameter_large_m: float = 0.450  # ASTM D6433 diameter edge 200-450 / 450-750 mm (m)
    crack_width_low_m: float = 0.006  # FHWA DIM crack width low/moderate: 6 mm (m)
    crack_width_high_m: float = 0.019  # FHWA DIM crack width moderate/high: 19 mm (m)
    rut_depth_low_m: float = 0.013  # ASTM D6433 rutting: low < 13 mm (m)
    rut_depth_high_m: float = 0.025  # ASTM D6433 rutting: high > 25 mm (m)

    # band edges above 1 m are unit mistakes (mm typed as m?)
    ORDER: ClassVar[tuple[tuple[str, str], ...]] = (
        ("depth_low_m", "depth_high_m"),
        ("diameter_small_m", "diameter_large_m"),
        ("crack_width_low_m", "crack_width_high_m"),
        ("rut_depth_low_m", "rut_depth_high_m"),
    )
    RANGES: ClassVar[dict[str, str]] = {
        "depth_low_m": "(0, 1]",
        "depth_high_m": "(0, 1]",
        "diameter_small_m": "(0, 10]",
        "diameter_large_m": "(0, 10]",
        "crack_width_low_m": "(0, 1]",
        "crack_width_high_m": "(0, 1]",
        "rut_depth_low_m": "(0, 1]",
        "rut_depth_high_m": "(0, 1]",
    }


@dataclass(frozen=True)
class MapSegmentConfig:
    """Segmentation and measurement on the global map (surface raster + refined points)."""

    depth_threshold_m: float = 0.008  # T_d floor on the map: seed cells deeper than this (m)
    noise_k: float = 4.0  # seeds: T_d = max(floor, noise_k * σ_map), σ_map = 1.4826 MAD (-)
    rim_threshold_m: float = 0.002  # outline floor: a defect extends while deeper than this (m)
    rim_noise_k: float = 1.5  # outline threshold = max(rim floor, rim_noise_k * σ_map) (unitless)
    rim_max_grow_frac: float = 0.5  # outline reaches <= this x the seeds' equivalent radius (-)
    rim_max_grow_min_m: float = 0.02  # ... or at least this far from the seeds (m)
    # outline parts on either side of an unknown strip at most 2 x this wide (m; 0 = off) are
    # one defect: below 50 % frame overlap a strip between two pairs' parts is seen by one frame
    # and left unknown next to relief (MappingConfig.dense_single_view_relief_m); a pothole across
    # it was split into one defect per pair, or kept whole by the chance of the mean shift
    # (7.5 m/s at 15 fps: a 13 cm strip). Only unknown cells bridge, never measured road
    bridge_unknown_m: float = 0.1
    level_window_m: float = 0.6  # re-level depths to the median road in this window (m); 0 = off
    level_ring_m: float = 0.2  # max depth: points are levelled to the road in this ring (m)
    smooth_m: float = 0.005  # Gaussian σ applied to the raster before thresholds (m); 0 = off
    fill_px: float = 1.0  # unobserved cells are filled from neighbours within about this σ (px)
    window_core_m: float = 1.0  # the map is read in windows around blocks of this size that hold
    # 3D defect evidence (m); memory grows with the defects, not the drive's bounding box
    window_margin_m: float = (
        1.0  # road read around each block for re-levelling, noise (m), >= level_window_m
    )
    fallback_gsd_m: float = 0.01  # grid size when RUN/surface.tif is absent (m)
    mean_shift_window_m: float = 0.30  # w: flat-kernel mean-shift window w x w (m), eq. 5.11
    # outline regions one mean-shift cluster holds are one defect only when at most this far
    # apart (m; their nearest cells), one inside the other, or with road below road level or
    # unknown between them (mapseg._joined): measured road wider than this between them is
    # two defects (two potholes 22 cm apart were one 1.65 m pothole; spd2 frames 12-13 and
    # 32-33, whose labels hold 2 and 4 separate potholes, read 2 and 2 defects, 1 and 1 with
    # 12 cm); 0 = every region of a cluster joins, as eq. 5.12 alone
    join_gap_m: float = 0.06
    # windows also open around groups of the dense surface's measured cells that pass the seed
    # test (detection.rasterseeds), not only around the pairs' deep sparse points: a shadowed
    # pothole floor gave the features nothing and was never looked at; False = off
    raster_seeds: bool = True
    mean_shift_max_iter: int = 50  # iterations per window (count)
    mean_shift_tol_m: float = 0.001  # a window has converged when it moves less (m)
    min_area_m2: float = 0.002  # drop defects whose deep area (>= seed threshold) is smaller (m²)
    min_depth_m: float = 0.010  # drop defects shallower than this at their deepest (m)
    min_support_pairs: int = 1  # 3D veto: defect points from at least this many pairs (count)
    min_support_points: int = 3  # 3D veto: and at least this many defect points in all (count)
    point_support_radius_m: float = 0.02  # a point supports a region within this distance (m)
    crack_max_width_m: float = 0.06  # narrower elongated defects are cracks (m)
    rut_min_length_m: float = 1.0  # longer elongated, wider defects are ruts (m)
    elongation_min: float = 3.0  # length / width above this = elongated (crack or rut) (unitless)
    frame_depth_m: float = 0.010  # frame label: deeper than this counts (m); truth uses 10 mm
    frame_min_area_m2: float = 0.002  # frame label: footprint holds at least this deep area (m²)

    ORDER: ClassVar[tuple[tuple[str, str], ...]] = (("rim_threshold_m", "depth_threshold_m"),)
    RANGES: ClassVar[dict[str, str]] = {
        "depth_threshold_m": "[0, 1]; a T_d above 1 m is a unit mistake (mm typed as m?)",
        "noise_k": "[0, inf)",
        "rim_threshold_m": "[0, 1]",
        "rim_noise_k": "[0, inf)",
        "rim_max_grow_frac": "[0, inf)",
        "rim_max_grow_min_m": "[0, inf)",
        "bridge_unknown_m": "[0, 1]; a strip over 2 m wide is not a gap between two views",
        "level_window_m": "[0, inf); 0 = off",
        "level_ring_m": "(0, inf)",
        "smooth_m": "[0, 1]; 0 = off",
        "fill_px": "[0, inf)",
        "window_core_m": "(0, inf)",
        "window_margin_m": "[0, inf)",
        "fallback_gsd_m": "(0, 1]; a raster cell above 1 m is a unit mistake",
        "mean_shift_window_m": "(0, inf)",
        "join_gap_m": "[0, inf); 0 = off",
        "mean_shift_max_iter": "[1, inf)",
        "mean_shift_tol_m": "(0, inf)",
        "min_area_m2": "[0, inf)",
        "min_depth_m": "[0, 1]",
        "min_support_pairs": "[0, inf)",
        "min_support_points": "[0, inf)",
        "point_support_radius_m": "[0, inf)",
        "crack_max_width_m": "[0, inf)",
        "rut_min_length_m": "[0, inf)",
        "elongation_min": "[1, inf); length / width",
        "frame_depth_m": "[0, 1]",
        "frame_min_area_m2": "[0, inf)",
    }


@dataclass(frozen=True)
class RutConfig:
    """Ruts traced on transverse profiles under a straightedge (see detection/ruts.py)."""

    enabled: bool = True  # trace elongated regions as ruts (False: ruts are plain map regions)
    straightedge_m: float = 1.2  # transverse profile length (m); FHWA LTPP's 1.2 m straightedge
    strip_m: float = 0.10  # each profile averages the raster over this length along the rut (m)
    step_m: float = 0.05  # station spacing along the rut (m)
    profile_smooth_m: float = 0.01  # Gaussian σ along the profile (m)
    trace_min_m: float = 0.003  # a station is in the rut when deeper than this (m) ...
    trace_noise_k: float = 4.0  # ... and than k x its profile's σ (unitless)
    min_width_m: float = 0.10  # trough width (at depth 0) at least (m): narrower is a crack
    max_width_m: float = 1.0  # ... and at most (m): wider is a sag, not a wheel-path rut
    min_road_side_m: float = 0.05  # observed road under the straightedge on each side (m)
    follow_m: float = 0.10  # the trough centre is searched this far from the predicted one (m)
    direction_stations: int = 6  # the direction follows the centre line over this many stations
    max_gap_m: float = 0.25  # tracing stops after this length of stations out of the rut (m)
    # Flat road between two troughs (potholes in a line, not a rut): at least flat_gap_m (m)
    # of stations shallower than flat_gap_frac (unitless) x the deepest station within
    # flat_gap_ref_m (m) on either side. A rut's length is its longest stretch between them
    flat_gap_m: float = 0.10
    flat_gap_frac: float = 0.25
    flat_gap_ref_m: float = 0.5
    # ... or after this length of unobserved road (a hole in the map: no evidence either way;
    # frames overlapping by less than half leave such holes between the pairs) (m)
    max_unobserved_m: float = 1.0
    # extend the traced length beyond each end by the depth ramp extrapolated to 0 (from where
    # it crosses t and 2t, t the trace threshold), like the width; False: the length of the
    # stations deeper than t only
    extrapolate_ends: bool = True
    max_length_m: float = 100.0  # tracing stops after this length in each direction (m)
    seed_min_length_m: float = 0.2  # regions at least this long (±2σ of their cells) seed (m)
    seed_elongation: float = 2.0  # ... and this elongated (length / width) (unitless)
    # A compact region seeds when some direction's trough is this much wider than the region
    # (a piece of a shallow rut; a pothole is its own trough), directions tried over 180° (-)
    seed_width_ratio: float = 2.0
    seed_directions: int = 8  # (count)
    depth_window_m: float = 0.25  # rut depth: largest median of the stations over this (m)
    # Ruts too shallow to cross T_d anywhere are seeded by a scan of transverse profiles along
    # the drive: a line every scan_step_m (m; 0 = no scan), stations up to scan_half_width_m
    # either side of the footprint centres (m)
    scan_step_m: float = 0.5
    scan_half_width_m: float = 0.6
    # report ruts at least this deep (m): ASTM D6433 rates rutting low from 6 mm (1/4 in)
    min_depth_m: float = 0.006

    ORDER: ClassVar[tuple[tuple[str, str], ...]] = (("min_width_m", "max_width_m"),)
    RANGES: ClassVar[dict[str, str]] = {
        "straightedge_m": "(0, inf)",
        "strip_m": "(0, inf)",
        "step_m": "(0, inf)",
        "profile_smooth_m": "[0, inf)",
        "trace_min_m": "[0, 1]",
        "trace_noise_k": "[0, inf)",
        "min_width_m": "[0, inf)",
        "max_width_m": "(0, inf)",
        "min_road_side_m": "[0, inf)",
        "follow_m": "[0, inf)",
        "direction_stations": "[1, inf)",
        "max_gap_m": "[0, inf)",
        "flat_gap_m": "[0, inf)",
        "flat_gap_frac": "[0, 1]",
        "flat_gap_ref_m": "[0, inf)",
        "max_unobserved_m": "[0, inf)",
        "max_length_m": "(0, inf)",
        "seed_min_length_m": "[0, inf)",
        "seed_elongation": "[1, inf); length / width",
        "seed_width_ratio": "[0, inf)",
        "seed_directions": "[1, inf)",
        "depth_window_m": "(0, inf)",
        "scan_step_m": "[0, inf); 0 = no scan",
        "scan_half_width_m": "[0, inf)",
        "min_depth_m": "[0, 1]",
    }


@dataclass(frozen=True)
class DetectionConfig:
    """Defect detection: per pair (Ch. 4), on the global map (§5.4), outputs for GIS."""

    plane: PlaneFitConfig = field(default_factory=PlaneFitConfig)
    refine: RefineConfig = field(default_factory=RefineConfig)
    map: MapSegmentConfig = field(default_factory=MapSegmentConfig)
    severity: SeverityConfig = field(default_factory=SeverityConfig)
    crack: CrackConfig = field(default_factory=CrackConfig)
    dense: DenseConfig = field(default_factory=DenseConfig)
    rut: RutConfig = field(default_factory=RutConfig)
    use_images: bool = True  # read frames for the 2D refinement (False: 3D only)
    # threads analysing the pairs (plane fit, 2D refinement, cracks) and measuring a defect
    # from the pairs that see it (dense; count): results are taken in pair order, identical
    # on any count
    pair_workers: int = 2
    # Frame labels: "map" = deep area of vetted map defects in the frame's footprint (default);
    # "pair" = the dissertation's per-pair decision from the refined points alone.
    frame_label: FrameLabelMode = "map"
    fusion_threshold: float = 0.95  # CNN decision stands when max(p) >= this (Fig. 5.6), 0.5-1
    overwrite: bool = False  # recompute even when RUN/defects.geojson exists

    RANGES: ClassVar[dict[str, str]] = {
        "pair_workers": "[1, inf)",
        "fusion_threshold": "[0.5, 1]; max(p) of two classes is at least 0.5",
    }
