"""One table of the numerical tolerances the tests use, each with the reason for its value (cf. kornia's
testing/base.py). Import the TOL instance; do not scatter bare literals through the tests."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Tolerances:
    """Named absolute/relative tolerances; units are in the name."""

    # A float64 closed form evaluated two ways (the module vs. the test's own arithmetic): only rounding
    # differs, a few ulps of O(1..100) values, so 1e-12 is loose enough and still catches any real slip.
    float64_abs: float = 1e-12

    # Two direct factorizations of the same symmetric positive definite normal equations (the pose graph's, its
    # 1e-9 ridge allowing conditions up to ~1e9): only rounding differs, measured <= 2e-12 on the shared scans' and
    # a 2400-frame examination's final passes (bench/pose_graph_solve.py); 1e-9 catches any wrong solve.
    linear_solve_abs: float = 1e-9

    # `best` on the realistic simulated short scan (seed 1), two-sided (OpenSfM-style band): >= 0.02 mm
    # (0.16 px: below the pose noise expected from keypoints on smooth vein maps chained over 40 frames, i.e.
    # a suspiciously perfect answer, e.g. truth leaking into the pipeline) and <= 0.35 mm (measured 0.24 mm
    # there: the simulated tissue is 6 % softer than calibrated and the compliance prior keeps the fit near the
    # calibration on 40 frames; 0.19 mm on the shared short_veins_21 scan), so a simulator that became much
    # easier or harder than the real frames would show on either side.
    best_short_rmse_mm: tuple[float, float] = (0.02, 0.35)

    # `best` on the simulated hard scan (seed 1: 200 frames at up to 30 N, rows 18 mm apart), the path's residual
    # after the best 2x2 linear map (what remains once the global scale/shear of the tissue law is taken out):
    # measured 0.67 mm with loop closures gated at 6 mm, 1.89 mm at 3 mm (the last rows closed no loop and
    # drifted to 8.5 mm); 0.39 mm once confirmed closures need 10 inliers, 0.25 mm with edges measured at their
    # inliers. <= 1.2 mm fails the old gate with margin; >= 0.2 mm flags a task made too easy.
    hard_shape_residual_mm: tuple[float, float] = (0.2, 1.2)

    # `best` on the shared short_veins_21 scan (40 frames, 154 mm, loads 4-18 N): measured 0.051 mm with the linear
    # tissue law, 0.096 mm when its weak curvature (chi2 4.8 against ln 40 = 3.7) was adopted as stiffening (the
    # path 0.20 % too large instead of 0.10 %); 0.062 mm once each frame's scale is held to the law (scale_prior);
    # 0.016 mm once frame 0 is held to the law's scale too (against 0.047 mm with the stiffening law then).
    # <= 0.035 mm fails the stiffening answer with margin; >= 0.005 mm (0.06 px) flags a suspiciously perfect one.
    shared_short_rmse_mm: tuple[float, float] = (0.005, 0.035)

    # `best` on the shared clinical_veins_24's first three strokes (seqs 0-160: two lifts, 28 frames in the air, 5
    # dropped; skin drag of up to 0.8 mm at 20 N along the strokes, which the path does not model yet): measured
    # 0.74 mm, of which 0.23 mm is the path's shape and the rest its scale (-0.68 %: the compliance gauge fitted on
    # 129 frames under drag). The clinical target is 0.5 mm (not met yet; docs/accuracy.md). <= 0.9 mm fails a
    # landing placed a vein (~1 mm) off; >= 0.05 mm flags a suspiciously perfect answer on frames dragged 0.1-0.8 mm.
    clinical_strokes_rmse_mm: tuple[float, float] = (0.05, 0.9)

    # `best` on the simulated scan in strokes (seed 1, linear law; no skin drag): measured 0.244 mm over 313 frames on
    # the skin (issue 30's target for scans with lifts and an island: <= 0.3 mm, which the upper bound is); >= 0.05
    # mm flags a suspiciously perfect answer (the continuous simulated raster is 0.1-0.2 mm).
    sim_strokes_rmse_mm: tuple[float, float] = (0.05, 0.3)

    # `best` on the simulated short scan with skin drag (seed 1, linear law, a hand's tilt; drag 0.16 mm/N with a
    # 9 mm stuck core): measured 0.350 mm (0.416 mm with the drag not learned, fit_drag=false); the upper bound
    # leaves 15 % for other platforms' OpenCV, the lower flags a suspiciously perfect answer
    sim_short_drag_rmse_mm: tuple[float, float] = (0.1, 0.4)

    # `best` on the simulated raster with the strongest skin drag of the bench (seed 3, 0.22 mm/N): measured 0.511 mm
    # with 66 loop closures (1.915 mm and 9 closures with the closures gated about one similarity and the chain's
    # scale left free: the rows came apart). <= 0.9 mm fails a raster broken again; >= 0.25 mm flags a suspiciously
    # perfect answer (the milder seeds 1, 2 are at 0.27 and 0.21 mm).
    sim_raster_strong_drag_rmse_mm: tuple[float, float] = (0.25, 0.9)

    # `best` on the simulated dragged raster of seed 4 (0.12 mm/N): measured 1.098 mm, its path 0.58 % small and turned
    # 0.39 deg (31.1 mm when a global pass while the scan went on shrank every frame but frame 0 to half, and frame 0
    # was left 31 mm from the rest). <= 1.6 mm fails a map that shrinks again; >= 0.5 mm flags a suspiciously good
    # answer on a scan whose turn no change has yet removed (docs/accuracy.md, "Skin drag").
    sim_raster_drag_seed4_rmse_mm: tuple[float, float] = (0.5, 1.6)

    # `best` on the simulated short scan (seed 1, a patient with the linear law and a hand's tilt) whose veins are
    # a photograph's vessels (test_vein_texture.vessel_photo: 30 straight vessels): measured 0.266 mm, against
    # 0.293 mm over the procedural veins of the same scan. <= 0.6 mm says the registration does not depend on the
    # procedural network's look; >= 0.05 mm flags a task made too easy.
    photo_short_rmse_mm: tuple[float, float] = (0.05, 0.6)

    # Known answers written into the tests as decimal literals with 10+ significant digits (worked out by
    # hand in the comments); the literal itself is rounded at ~1e-10 relative, so compare at 1e-9 relative.
    hand_value_rel: float = 1e-9

    # deform_points_mm inverts rectification by fixed-point iteration (8 steps, contraction factor
    # ~ c |grad F| r ~ 1e-3 at the paper's constants): the residual is far below 1e-9 mm.
    fixed_point_mm: float = 1e-9

    # undistort(distort(p)) with OpenCV's iterative undistortion (eps 1e-9 in normalised units, 20
    # iterations): converges to ~1e-9 px at moderate distortion; the issue asks for 1e-3 px.
    undistort_roundtrip_px: float = 1e-3

    # distort_points_px vs. cv2.projectPoints: the same double-precision polynomial in both, so only
    # rounding differs (values ~ 1e3 px, a few ulps ~ 1e-13); 1e-6 px leaves room and catches any term error.
    project_points_px: float = 1e-6

    # Maps composed through rectify_map (float32 for cv2.remap: 640 px has a float32 spacing of ~6e-5 px)
    # and rectify_keypoints_px (iterative undistortion + fixed-point inverse): the 0.05 px budget.
    map_composition_px: float = 0.05

    # rectify_map evaluates the model every 8 px and interpolates bilinearly: the map is lens distortion plus a
    # load-proportional stretch, whose curvature over 8 px moves a sample by ~3e-3 px (measured at most
    # 0.0031 px over every fifth frame of both shared scans): 0.01 px keeps a margin and is 5x below the
    # 0.05 px composition budget above.
    map_interpolation_px: float = 0.01

    # Blob centres measured in a remapped image (one bilinear resampling of a smooth Gaussian, sigma 2.5 px,
    # intensity-weighted centroid): the 0.05 px budget for a deform-then-rectify round trip.
    feature_position_px: float = 0.05

    # Linear interpolation of forces whose exact answers are short decimals (N): float64 rounding only.
    force_interp_n: float = 1e-12

    # Vein maps (8-bit) of a frame and of the same frame times a gain of 1.3 and a +-30 % smooth shading: the
    # flat field divides both out, so only rounding of the 8-bit input and the skin level's finite width
    # differ. Measured mean 0.13 DN and 99th percentile 2 DN on the synthetic frame; without the flat field
    # the mean difference is tens of DN.
    vein_map_mean_dn: float = 0.5
    vein_map_p99_dn: float = 4.0

    # Direct alignment (phase correlation + ECC on half-resolution vein maps, 0.25 mm per work pixel) of two
    # synthetic views of one vein field, moving -> fixed. The maps differ near the window edge (erosion, the
    # skin level's support, the 8-bit range set by each window's own strongest vessel), which biases ECC by
    # a fraction of a work pixel: measured worst 0.082 mm, 0.067 deg, 0.0030 scale over 4 transforms x 3
    # seeds (typically 0.005-0.03 mm). Tolerances ~2x the worst: a slip of 1 work pixel (0.25 mm) fails.
    direct_shift_mm: float = 0.15
    direct_yaw_deg: float = 0.15
    direct_scale: float = 0.006

    # The compliance fit's strain law (services/core/physics/compliance.py) on per-frame scales made from a known
    # law, 300 frames over 2-26 N (the shared scans' load range) with 0.2 % log-normal scale noise (their scatter
    # about the fit is 0.08-0.21 %). A stiffening law eps = c F / (1 + F / 40 N), least squares: measured worst
    # 3.0 % strain error at 5-20 N over 20 seeds (0.3 % at 1-20 N on the test's seed) and 0.10 % gauge error;
    # with the default 5 % prior on the secant compliance at the mean load (where this tissue is 23 % stiffer
    # than nominal, 6 % softer at no load) 5.0 % (2.2 % on the test's seed) and 0.28 % (0.17 %). The linear law's
    # gauge is 1.2-1.4 % off there, so either budget fails without the stiffening term.
    law_strain_rel: float = 0.06
    law_gauge_ls_rel: float = 0.002
    law_gauge_prior_rel: float = 0.004
    # Laws of other shapes than the fit's (normalised at 10 N as the simulator's): the stiffening fit's gauge
    # error as a fraction of the linear fit's. Measured worst over 20 seeds 0.54 for a power law F^0.8 (its
    # infinite slope at no load is half captured; 0.48-0.50 on the test's 3 seeds) and 0.14 for Fung's
    # logarithmic toe, F_e = 12 N (0.08-0.10).
    law_power_gauge_ratio: float = 0.65
    law_toe_gauge_ratio: float = 0.25
    # ... and a saturating law, strain (1 - exp(-F / 6 N)) at 10 N, fitted by the saturating shape: measured worst
    # over 20 seeds 0.075 (0.016-0.039 on the test's 3 seeds).
    law_saturating_gauge_ratio: float = 0.15
    # The fraction of 300 least-squares fits whose truth lies within the reported 68 % half-width (Laplace,
    # from the posterior's curvature): measured 0.64-0.68 for c, s and the gauge (binomial sd 0.027); the band
    # catches a half-width 1.5x too wide (0.87 expected) or too narrow (0.50).
    law_coverage_68: tuple[float, float] = (0.55, 0.8)

    # A live session's mosaic after its finish against a whole restitch at the final poses (issue 32's decision: live
    # is a reprocess within a tolerance): frames within FINISH_MOVED_PX (0.25 px) of their final place are not
    # pasted again, which moves a vein edge's grey by a fraction of a level; one level at every pixel is the promise,
    # at every pixel whose blend weight in the whole restitch is restitch_firm_weight or more. Below it only the
    # faint rim of one window covers the pixel (canvas.blend_weight: ramp x centre preference; a mosaic pixel's median
    # weight is about 18), and its grey is a ratio of two near-zero sums that a tenth of a pixel's move changes by
    # levels: on the simulated raster kept at finishes run ahead (336 frames, a run every 30), 439 of 2.6 M pixels
    # were more than a level off, every one of weight below 0.016.
    finish_restitch_grey: float = 1.0
    restitch_firm_weight: float = 0.025


TOL = Tolerances()
