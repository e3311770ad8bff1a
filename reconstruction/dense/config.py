"""Configuration of the dense two-view height (``reconstruction.dense``). Frozen dataclass, every
field with its unit; ranges in ``RANGES`` (see ``roadsurf.core.config``)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

from roadsurf.core.camera import capped_scale

# the second, deeper search never goes below this share of the camera's height: weak texture
# can start a patch at the bottom too (spd2's 0.5 m camera: two of 26 pairs, searched down to
# 480 mm before)
DEEP_MAX_HEIGHT_SHARE = 0.5


@dataclass(frozen=True)
class DenseHeightConfig:
    """Plane + parallax matching of one pair (``reconstruction.dense.parallax``)."""

    # work on images resized by this (−, <= 1; 0.5 = a quarter of the pixels); the output
    # height map has the work grid's size
    scale: float = 1.0
    # ... and at most this many megapixels (Mpx; 0 = off; scales >= 0.95 are not applied, so
    # 640 x 480 stays whole). The matching window must span the road's grain: on real
    # photographs a 5 px window at full size (spd2, 1720 x 1030, a road ~0.3 mm per pixel) sees
    # smooth ramps and matches 7-16 % of the road around a pothole and 0-2 % of its floor;
    # at 0.3 Mpx (scale 0.41) 60-79 % and 4-31 %, 10x faster (the cap of the features too)
    max_megapixels: float = 0.3
    # where the search starts: "sweep" = ZNCC plane sweep over heights (torch, global within
    # the height range, robust on weak texture), "dis" = OpenCV DIS optical flow projected on
    # the epipolar direction (CPU only; fast, coarse-to-fine, can lose small low-texture spots)
    init: Literal["sweep", "dis"] = "sweep"
    sweep_scale: float = 0.25  # the sweep runs on the work grid resized by this (−, <= 1),
    sweep_min_px: int = 120  # ... but on at least this many pixels along the shorter side (px)
    sweep_step_px: float = 0.5  # largest parallax step between swept heights (px, sweep grid)
    max_depth_m: float = 0.12  # deepest point below the road plane searched (m)
    # a pair whose sweep starts a patch of pixels at 90 % of max_depth_m or deeper
    # (``parallax.DEEP_*``) is matched again, once, down to this or half the camera height,
    # the shallower (m; <= max_depth_m = off): a 240-290 mm pothole read 107-128 mm, cut flat
    # at the search depth; a deeper search on every pair cost the map stage 21 %
    max_depth_limit_m: float = 0.48
    max_height_m: float = 0.06  # highest point above the road plane searched (m)
    window_px: int = 5  # side of the matching window (px at the work grid, odd)
    # σ of a Gaussian applied to both images before matching (px); on the simulated drives a
    # blur only lost precision (640 x 480: 0.7 px -> flat MAE 0.85 mm, 0 -> 0.81 mm)
    blur_px: float = 0.0
    refine_iters: int = 5  # 1D Lucas-Kanade steps along the epipolar line after the init (count)
    # a pixel's Lucas-Kanade has converged when its last step is at most 0.05 px or at most this
    # times the parallax σ it measures (−; 0 = 0.05 px only): a step within half the match's own
    # noise is below what the match can resolve, and its square is added to the variance (at
    # most +25 %). On spd2 a median 13 % of the labelled pothole pixels failed the 0.05 px test
    # alone (last step median 0.1 px, their σ 0.2 px)
    step_max_sigma: float = 0.5
    # slanted second pass (``dense.slanted``): pixels whose parallax gradient, a plane fitted
    # to the first pass over (window_px + 4)² px, is significant at this many σ of its own
    # noise (Wald z, −; 0 = off) are matched again in windows slanted by it. The plane-warped
    # road has no parallax, so a = 0 there and it keeps its first match; a steep defect wall
    # (parallax changing along the window) is matched without the fronto-parallel bias
    slant_sigmas: float = 3.0
    # a pixel whose window's accepted parallaxes (after the slanted pass) deviate from their
    # best plane by this RMS or more straddles a step (a pothole's rim in front of its floor, a
    # ridge of a rough floor): no slanted window describes it, its match is a mix of the two
    # surfaces, and it is refused (REJECT_GEOMETRY; px at the work grid, 0 = off). 0.5 px is
    # slanted.MIN_SPAN_PX: window samples that far off any one plane of parallax leave the
    # Lucas-Kanade's linear image model; about a 2 px step across a 5 px window. Seed-7 45°
    # stereo pair after the shifted windows (benchmarks.dense_pair_truth): 2.7 % of the
    # pothole's work-grid pixels, 31 % of its squared error (RMS 11 mm, +3.4 mm shallow); 0.1 %
    # of the road's. Without the shifted windows a fattened step looks like a ramp and few
    # pixels are refused. Pixels refused here or by the left-right check are not filled from
    # the coarser grid (``dense.pyramid``: a wider window straddles the step more)
    step_plane_px: float = 0.5
    # shifted windows (``dense.shifted``): accepted pixels next to an occlusion (a left-right
    # refusal) or whose window's parallaxes span >= 2 px take the match of the window that
    # holds them at an edge or corner, on their own side of a step (a pothole's rim in front of
    # its floor), where their own 3 x 3 neighbourhood correlates better at it. A centred window
    # straddling the step reads a mix of both sides. False = off
    shifted_windows: bool = True
    lr_check: bool = True  # match b -> a as well and keep pixels where both agree
    lr_max_px: float = 0.5  # largest left-right disagreement kept (px at the work grid)
    # Lucas-Kanade steps of the b -> a match, which only has to land within lr_max_px of the
    # forward one: 2 steps from the sweep kept the same pixels as 5 at 640 x 480 (count; < 0:
    # refine_iters)
    lr_refine_iters: int = 2
    min_ncc: float = 0.6  # smallest zero-mean normalised cross-correlation kept (−)
    min_grad_dn: float = 1.5  # smallest RMS image gradient along the epipolar line in the
    # window (DN/px at the work grid): below, textureless
    dark_dn: int = 2  # a window holding a pixel at or below this is under-exposed (DN)
    saturated_dn: int = 253  # a window holding a pixel at or above this is saturated (DN)
    noise_dn: float = 1.0  # floor on the image noise σ in the parallax variance (DN)
    # edge-preserving (bilateral) mean of the valid heights: spatial σ (px at the work grid;
    # 0 = off) and range σ (m). Most of the road is seen by one pair only, so each cell's height
    # is one window match; neighbouring windows' errors are partly independent, defect walls
    # (steps of several range σ) are kept. Off here (per-pixel heights, their variance is not
    # reduced); the dense surface sets 1.5 px (MappingConfig.dense), about the 5 px window's
    # own σ (5/√12 = 1.44 px): it averages the partly independent errors of overlapping
    # windows without widening the surface's resolution past one window. A wider σ trades the
    # floor of a pothole for a quieter road: tilted drive, same pairs, 3 -> 1.5 px, defect
    # depth MAE 1.95 / 2.45 / 3.13 -> 1.52 / 1.94 / 2.54 mm at 0 / 25 / 45°, flat MAE
    # 0.95 / 1.03 / 1.32 -> 0.89 / 1.01 / 1.38 mm (the pothole floors' 5-15 mm roughness is
    # smoothed away, their deepest point read shallow); 0 px reads the floor deeper still
    # (25°: 1.36 mm) but the road noisier (flat 1.05, in-defect 1.43 -> 1.53 mm)
    smooth_px: float = 0.0
    smooth_range_m: float = 0.003
    scale_rel_sigma: float = 0.003  # relative σ of the pair's metric scale (−): adds (η σ)²
    # pixels that fail on the work grid (low ZNCC, textureless, not converged, left-right
    # disagreement) are matched again on grids coarser by 2, 4, ... (this many; 0 = off; a grid
    # with fewer than sweep_min_px px along its shorter side is not used) and take the height
    # there, with its variance widened by the relief in its window (``dense.pyramid``: a wider
    # window fattens walls). The same window then spans 2^k x the ground: the coarser texture
    # correlates across a change of view where the fine grain does not (spd2, labelled pothole
    # pixels with a height, median of 26 pairs: 30 % -> 62 %, 67 % with step_max_sigma; coarse
    # minus fine where both pass +0.04 mm, MAD 0.4 mm). One level: a second one's window (20
    # work px, 2-4 cm of road) spans a pothole's wall
    fallback_levels: int = 1
    min_epipole_px: float = 8.0  # pixels closer than this to the epipole are invalid (px)
    device: str = "auto"  # torch device: "auto" (CUDA when present), "cpu", "cuda", "cuda:1"
    cpu_threads: int = 1  # torch threads while matching on the CPU (count; 0 = torch's own)
    # read by the dense surface's raster (mapping.rasterise.fill_inward), not by the matching:
    # cells left empty within this distance (m) of measured cells are filled from the measured
    # heights at their own edge, ring by ring, before the sparse fill (which then only fills
    # cells further away); a cell whose known neighbours span more than the surface's relief
    # limit (a pothole wall) stays empty. The LR check empties the occluded band of a pothole
    # wall (rim-to-floor parallax ~0.2 px per mm of depth at 1.1 m, f = 600 px, 0.4 m
    # baseline: 1-2 cm on the ground for a 40 mm pothole), and the sparse surface interpolated
    # across it read those cells shallow (potholes drive: 5,163 in-defect cells, MAE 9.6 mm,
    # bias +7.5 mm); 0 = off
    hole_fill_m: float = 0.02

    def deepest_search_m(self, camera_height_m: float) -> float:
        """The deepest height below the road plane any pair is matched down to (m):
        ``max_depth_m``, or the second search's when ``max_depth_limit_m`` allows one (at most
        ``DEEP_MAX_HEIGHT_SHARE`` of the camera height). surface.tif names it: a cell that deep
        may be deeper."""
        second = min(self.max_depth_limit_m, DEEP_MAX_HEIGHT_SHARE * camera_height_m)
        return max(self.max_depth_m, second)

    def work_scale(self, width: int, height: int) -> float:
        """The work grid's scale for images of width x height px: ``scale``, lowered so the
        grid holds at most ``max_megapixels`` (``core.camera.capped_scale``)."""
        return capped_scale(self.scale, width, height, self.max_megapixels)

    RANGES: ClassVar[dict[str, str]] = {
        "scale": "(0, 1]",
        "max_megapixels": "[0, inf); 0 = off",
        "init": "{sweep, dis}",
        "sweep_scale": "(0, 1]",
        "sweep_min_px": "[16, inf)",
        "sweep_step_px": "(0, 4]; a coarser sweep steps over the ZNCC peak",
        "max_depth_m": "[0, 1]; a search deeper than 1 m is a unit mistake",
        "max_height_m": "[0, 1]",
        "max_depth_limit_m": "[0, 1]; a search deeper than 1 m is a unit mistake",
        "window_px": "[3, 31]",
        "blur_px": "[0, 5]",
        "refine_iters": "[0, 50]",
        "step_max_sigma": "[0, 2]",
        "slant_sigmas": "[0, inf); 0 = off",
        "step_plane_px": "[0, inf); 0 = off",
        "lr_max_px": "(0, inf)",
        "lr_refine_iters": "[-1, 50]; -1 = refine_iters",
        "min_ncc": "[-1, 1]",
        "min_grad_dn": "[0, inf)",
        "dark_dn": "[0, 255]",
        "saturated_dn": "[0, 255]",
        "noise_dn": "(0, inf)",
        "smooth_px": "[0, 20]",
        "smooth_range_m": "(0, 1]",
        "scale_rel_sigma": "[0, 1]",
        "fallback_levels": "[0, 4]",
        "min_epipole_px": "[0, inf)",
        "cpu_threads": "[0, 1024]; 0 = leave torch's setting",
        "hole_fill_m": "[0, inf); 0 = off",
    }
