"""Simulated scans with known truth: `simulate(scenario, seed)` returns a Scan with frames in memory."""

from __future__ import annotations

import dataclasses
from types import MappingProxyType

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.inputs.scan import Scan, in_memory_loader
from services.core.physics.force_model import LoadState
from services.core.simulation.probe_path import (
    ProbeMotion,
    calibration_motion,
    free_hand_motion,
    path_length_mm,
    rotation,
    scenario_motion_spec,
    smooth_noise,
)
from services.core.simulation.renderer import (
    TISSUE_LAWS,
    Imaging,
    TissueLaw,
    apply_imaging,
    frame_geometry,
    motion_blur_kernel,
    render_scene,
)
from services.core.simulation.skin_drag import draw_skin_drag, frame_drags_mm
from services.core.simulation.strokes import (
    air_frame,
    clock_skew_s,
    dropped_frames,
    stroke_length_mm,
    stroked_motion,
)
from services.core.simulation.variants import ImagingVariant, scenario_imaging
from services.core.simulation.vein_texture import make_photo_world, make_world

SCENARIOS = ("raster", "revisit", "hard", "short", "calib")
LONG_SCENARIOS = ("exam",)  # minutes long (2400 frames by default): for the long-examination bench, not test loops
# scanned as a clinician scans (services.core.simulation.strokes): lifts, frames in the air, an island, dropped
# frames, a skewed force clock
STROKE_SCENARIOS = ("strokes",)
ALL_SCENARIOS = SCENARIOS + LONG_SCENARIOS + STROKE_SCENARIOS

NOMINAL_E_KPA = 16.1
NOMINAL_KAPPA_N_PER_MM = 18.0
# a texture photograph's pixel on the skin: a fundus photograph's widest vessels (~15 px) become ~5 mm veins
TEXTURE_MM_PER_PX = 0.375
TRUE_KAPPA_N_PER_MM = (0.1, 0.3)  # the effective kappa of a hand on tissue, log-uniform (draw_hand_kappa)
HAND_TILT_DEG = MappingProxyType(
    {
        "raster": 10.0,
        "revisit": 10.0,
        "hard": 15.0,
        "short": 7.0,
        "exam": 10.0,
        "strokes": 10.0,
    }
)  # as the shared scans' README
# a hand that turns the probe by up to this much (deg) either way over tissue whose anisotropy is fixed in it
TISSUE_AXIS_YAW_DEG = 15.0
FORCE_RATE_HZ = 100.0
FORCE_NOISE_N = 0.03
FORCE_OFFSET_N = 0.1  # per-sensor constant offset, uniform in [-0.1, 0.1] N
IMU_RATE_HZ = 50.0
IMU_NOISE_DEG = 0.01
STREAM_MARGIN_S = 0.5  # force and IMU streams start this long before the first frame and end after the last
WORLD_MARGIN_MM = 60.0  # the world extends this far beyond every frame centre (half-diagonal of the view + slack)
GAIN_DRIFT_TAU_FRACTION = 0.3  # the slow gain drift's time scale, as a fraction of the scan's frame count


def nominal_calibration() -> Calibration:
    """Return the simulated probe's calibration: its lens model and the NOMINAL force constants of spec §2."""
    return Calibration(
        image_size=(640, 480),
        camera_matrix=((520.0, 0.0, 318.3), (0.0, 520.0, 238.6), (0.0, 0.0, 1.0)),
        px_per_mm=8.0,
        dist_coeffs=(-0.03, 0.004, 0.0003, -0.0002, 0.0),
        young_modulus_kpa=NOMINAL_E_KPA,
        poisson_ratio=0.5,
        hooke_n_per_mm=NOMINAL_KAPPA_N_PER_MM,
        sensor_separation_mm=(53.0, 53.0),
        scanner_area_m2=0.0048,
    )


def draw_true_constants(rng: np.random.Generator) -> tuple[float, float]:
    """Return (E_true kPa, kappa_true N/mm): 4-10% off the nominal E, up to 10% off the nominal kappa."""
    d = rng.uniform(0.04, 0.10) * rng.choice([-1.0, 1.0])
    d2 = rng.uniform(-0.10, 0.10)
    return NOMINAL_E_KPA * (1.0 + d), NOMINAL_KAPPA_N_PER_MM * (1.0 + d2)


def draw_hand_kappa(rng: np.random.Generator) -> float:
    """Return an effective kappa (N/mm) of a hand on tissue, log-uniform in TRUE_KAPPA_N_PER_MM.

    The calibration's kappa (18 N/mm) is one phantom's: a hand-held probe tilts by degrees for a few newtons of
    force difference, which the shared scans' trackers put at 0.13-0.17 N/mm (spec §2: a per-patient unknown).
    """
    return float(np.exp(rng.uniform(*np.log(TRUE_KAPPA_N_PER_MM))))


def draw_tissue_law(rng: np.random.Generator, kind: str, compliance_per_n: float) -> TissueLaw:
    """Return the true tissue law of a kind in TISSUE_LAWS: linear is spec §2's isotropic law; the others
    stiffen (half strain at 25-60 N, a power 0.7-0.9, or a logarithmic toe of 8-20 N) and stretch 3-8 % more along
    one axis than the other, the frame's x or y; saturating levels off above 4-10 N (TissueLaw) and its axis, at
    any angle, is fixed in the tissue (in the frame it turns against the probe's yaw)."""
    if kind not in TISSUE_LAWS:
        raise ValueError(f"unknown tissue law {kind!r}; expected one of {', '.join(TISSUE_LAWS)}")
    if kind == "linear":
        return TissueLaw(kind, compliance_per_n)
    anisotropy = float(rng.uniform(0.03, 0.08) * rng.choice([-1.0, 1.0]))
    half_n, exponent = float(rng.uniform(25.0, 60.0)), float(rng.uniform(0.7, 0.9))
    toe_n = float(rng.uniform(8.0, 20.0)) if kind == "toe" else TissueLaw.toe_n  # drawn last: the others unchanged
    if kind != "saturating":
        return TissueLaw(kind, compliance_per_n, half_n, exponent, anisotropy, toe_n)
    sat_n, angle = float(rng.uniform(4.0, 10.0)), float(rng.uniform(-90.0, 90.0))
    return TissueLaw(kind, compliance_per_n, half_n, exponent, anisotropy, toe_n, sat_n, "tissue", angle)


def _stream_times(rng: np.random.Generator, t_first: float, t_last: float, rate_hz: float) -> np.ndarray:
    """Return jittered, strictly increasing sample times (s) at ~rate_hz covering the frames +-0.5 s."""
    period = 1.0 / rate_hz
    n = int(np.floor((t_last - t_first + 2 * STREAM_MARGIN_S) / period)) + 1
    t = t_first - STREAM_MARGIN_S + period * np.arange(n)
    jitter = rng.uniform(-0.2 * period, 0.2 * period, n)
    jitter[0] = jitter[-1] = 0.0
    return t + jitter


def frame_poses(motion: ProbeMotion) -> tuple[np.ndarray, np.ndarray]:
    """Return (positions (N, 2) mm, yaw (N,) deg) of every frame in frame 0's coordinates (spec §4)."""
    back = rotation(-float(motion.yaw_deg[0]))
    xy = (motion.centre_mm - motion.centre_mm[0]) @ back.T
    return xy, motion.yaw_deg - motion.yaw_deg[0]


def frame_gains(rng: np.random.Generator, n: int, imaging: ImagingVariant) -> np.ndarray:
    """Return n exposure gains (fraction, ~1): a slow drift spanning imaging.gain_drift plus per-frame jitter."""
    drift = imaging.gain_drift * smooth_noise(rng, n, max(1.0, GAIN_DRIFT_TAU_FRACTION * n), -0.5, 0.5)
    return 1.0 + drift + rng.uniform(-imaging.gain_jitter, imaging.gain_jitter, n)


def motion_angles_deg(motion: ProbeMotion) -> np.ndarray:
    """Return the direction (deg, image axes) in which the skin moves across each frame (motion blur's axis)."""
    n = len(motion)
    if n < 2:
        return np.zeros(n)
    velocity = np.gradient(motion.centre_mm, axis=0)
    angles = np.empty(n)
    for k in range(n):
        v = rotation(-float(motion.yaw_deg[k])) @ velocity[k]  # world mm -> frame k's image axes
        angles[k] = np.rad2deg(np.arctan2(v[1], v[0]))
    return angles


def resolve_imaging(scenario: str, imaging: ImagingVariant | str) -> ImagingVariant:
    """Return imaging itself, or the scenario's ImagingVariant for a variant name (VARIANTS)."""
    return scenario_imaging(scenario, imaging) if isinstance(imaging, str) else imaging


def simulate(
    scenario: str,
    seed: int,
    imaging: ImagingVariant | str = "realistic",
    tissue: str | None = None,
    frames: int | None = None,
    imu: bool = False,
    texture: np.ndarray | None = None,
    drag: bool = False,
    radial: float | None = None,
) -> Scan:
    """Return a simulated Scan (frames in memory) of a scenario in SCENARIOS, deterministic for the seed.

    imaging: a variant name ("realistic", the default that looks like the shared NIR scans; "faint";
    "textured", the easy fine-grain skin) or an ImagingVariant. The motion, forces and truth poses depend only
    on (scenario, seed), never on the imaging. truth: young_modulus_kpa, hooke_n_per_mm (the true constants),
    poses [[x_mm, y_mm, yaw_deg], ...] in frame 0's coordinates, fz_n and tilt_x_deg / tilt_y_deg per frame,
    blurred frame indices, blur_px per frame (0 = sharp), gains per frame, path_length_mm, force_offsets_n,
    imaging (the variant as a dict), scenario, seed, tissue (the law, TissueLaw.to_dict), and for an
    anisotropy axis fixed in the tissue anisotropy_angle_frame0_deg (the axis in frame 0's axes).
    tissue: None for the phantom the project's bands were measured on (spec §2's linear law, the calibration's
    kappa +-10 %, tilts under 0.3 deg); a law in TISSUE_LAWS for a patient as on the shared scans: a hand's
    effective kappa (draw_hand_kappa), tilts up to HAND_TILT_DEG (a tilted view: 1/cos along the tilt) and the
    law's shape and anisotropy. reference_angles_deg: yaw relative to frame 0 and the true tilts, as a tracker.
    frames: the number of frames of an "exam" (default 2400: 4 minutes at 10 frames/s); other scenarios have theirs.
    imu: give the scan an IMU stream of the true tilts (imu.csv; the "calib" scenario always has one): the
    shared scans have none, so by default the tilt must come from the images.
    texture: a photograph (grayscale or BGR, 8/16 bit) whose dark vessels become the veins instead of the
    procedural network (a fundus photograph: the "real retinal vessel texture" of issue 14's hidden raster), at
    TEXTURE_MM_PER_PX; truth["texture"] says which.
    drag: the skin is dragged by friction under the sliding window (simulation.skin_drag: stick-slip, a
    centre-to-rim profile); the reference is then where the skin under the window's centre rests, and truth
    gains "drag" (the profile) and "drag_mm" (each frame's drag at the centre, its axes).
    radial: the strain's growth towards the window's rim that spec §2 does not have (TissueLaw.radial; None: the
    renderer's UNMODELLED_RADIAL). The shared scans show none (docs/accuracy.md); 0 renders without it.
    """
    if scenario not in ALL_SCENARIOS:
        raise ValueError(f"unknown scenario {scenario!r}; expected one of {', '.join(ALL_SCENARIOS)}")
    if frames is not None and (scenario != "exam" or frames < 24):
        raise ValueError("frames: only an exam's length can be chosen, at least 24 frames")
    look = resolve_imaging(scenario, imaging)
    cv2.setRNGSeed(int(seed) & 0x7FFFFFFF)
    rng_const, rng_path, rng_world, rng_img, rng_stream, rng_drag = (  # spawned children: the first five
        np.random.default_rng(s) for s in np.random.SeedSequence([int(seed), ALL_SCENARIOS.index(scenario)]).spawn(6)
    )  # are the same whatever the count, so a scan with drag is the same scan otherwise
    calib = nominal_calibration()
    e_true, kappa_true = draw_true_constants(rng_const)
    spec = scenario_motion_spec(scenario, frames) if scenario not in ("calib", *STROKE_SCENARIOS) else None
    if tissue is not None:
        kappa_true = draw_hand_kappa(rng_const)
        spec = spec and dataclasses.replace(spec, max_tilt_deg=HAND_TILT_DEG[scenario])
    true_calib = calib.with_overrides(young_modulus_kpa=e_true, hooke_n_per_mm=kappa_true)
    law = draw_tissue_law(rng_const, tissue or "linear", true_calib.compliance_per_n)
    if radial is not None:
        law = dataclasses.replace(law, radial=float(radial))
    if law.anisotropy_axis == "tissue" and spec is not None:  # the probe yaws: the tissue's axis turns in its frames
        spec = dataclasses.replace(spec, yaw_amplitude_deg=max(spec.yaw_amplitude_deg, TISSUE_AXIS_YAW_DEG))
    sep = calib.sensor_separation_mm

    in_air: np.ndarray | None = None
    if scenario == "calib":
        motion = calibration_motion(rng_path, kappa_true, sep)
    elif scenario in STROKE_SCENARIOS:
        stroked = stroked_motion(rng_path, kappa_true, sep, HAND_TILT_DEG[scenario] if tissue is not None else 0.3)
        motion, in_air = stroked.motion, stroked.in_air
    else:
        assert spec is not None
        motion = free_hand_motion(rng_path, spec, kappa_true, sep)
    n = len(motion)

    lo = motion.centre_mm.min(axis=0) - WORLD_MARGIN_MM
    hi = motion.centre_mm.max(axis=0) + WORLD_MARGIN_MM
    bounds = (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]))
    if texture is None:
        world = make_world(rng_world, bounds, calib.px_per_mm, look.vessel_contrast, look.textured_skin)
    else:
        world = make_photo_world(rng_world, bounds, texture, TEXTURE_MM_PER_PX, calib.px_per_mm, look.vessel_contrast)

    geometry = frame_geometry(calib)
    fz, tx, ty = motion.load_at(motion.frame_t_s)
    on_skin = ~in_air if in_air is not None else np.ones(n, bool)
    if law.kind != "linear":  # the calibration's E is the secant compliance at the scan's typical load
        law = dataclasses.replace(law, anchor_n=float(np.mean(fz[on_skin])))
    blurred_flags = rng_img.random(n) < look.blur_fraction
    blurred_flags[0] = False
    if in_air is not None:
        blurred_flags &= ~in_air  # frames in the air are defocused instead (air_frame)
    blur_px = np.where(blurred_flags, rng_img.integers(look.blur_length_px[0], look.blur_length_px[1] + 1, n), 0)
    blurred_flags &= blur_px > 1  # a 1-px "streak" is no blur
    angles = motion_angles_deg(motion) + rng_img.normal(0.0, 10.0, n)  # the hand's jitter about the motion
    gains = frame_gains(rng_img, n, look)
    skin_drag = draw_skin_drag(rng_drag) if drag else None
    drags = frame_drags_mm(rng_drag, skin_drag, motion, fz, on_skin) if skin_drag else np.zeros((n, 2))
    frames = []
    for k in range(n):
        kernel = motion_blur_kernel(int(blur_px[k]), float(angles[k])) if blur_px[k] > 1 else None
        frame_imaging = Imaging(noise_dn=look.noise_dn, gain=float(gains[k]), blur_kernel=kernel, dtype=look.dtype)
        state = LoadState(float(fz[k]), float(tx[k]), float(ty[k]))
        dragged = (skin_drag, drags[k]) if skin_drag is not None else None
        scene = render_scene(
            world, geometry, motion.centre_mm[k], float(motion.yaw_deg[k]), state, true_calib, law, dragged
        )
        if in_air is not None and in_air[k]:
            scene = air_frame(scene, rng_img)
        frames.append(apply_imaging(scene, geometry, frame_imaging, rng_img))

    t_first, t_last = float(motion.frame_t_s[0]), float(motion.frame_t_s[-1])
    force_t = _stream_times(rng_stream, t_first, t_last, FORCE_RATE_HZ)
    offsets = rng_stream.uniform(-FORCE_OFFSET_N, FORCE_OFFSET_N, 4)
    true_forces = motion.sensor_forces_at(force_t, kappa_true, sep)
    forces = true_forces + offsets + rng_stream.normal(0.0, FORCE_NOISE_N, true_forces.shape)
    imu_t = _stream_times(rng_stream, t_first, t_last, IMU_RATE_HZ)
    _, itx, ity = motion.load_at(imu_t)
    imu_deg = np.rad2deg(np.stack([itx, ity], axis=1)) + rng_stream.normal(0.0, IMU_NOISE_DEG, (len(imu_t), 2))
    with_imu = imu or scenario == "calib"
    skew = clock_skew_s(rng_stream) if in_air is not None else 0.0  # the force logger's clock, off the camera's
    dropped = dropped_frames(rng_stream, n) if in_air is not None else np.zeros(n, bool)

    rest = motion.centre_mm - np.einsum("kij,kj->ki", np.stack([rotation(float(a)) for a in motion.yaw_deg]), drags)
    xy, yaw = frame_poses(dataclasses.replace(motion, centre_mm=rest))  # the skin under the centre, at rest
    angles_deg = np.stack([yaw, np.rad2deg(tx), np.rad2deg(ty)], axis=1)
    if in_air is not None:  # a tracker's reference has no row for a frame taken in the air
        xy[in_air] = np.nan
        angles_deg[in_air] = np.nan
    kept = np.flatnonzero(~dropped)
    truth = {
        "scenario": scenario,
        "seed": int(seed),
        "young_modulus_kpa": float(e_true),
        "hooke_n_per_mm": float(kappa_true),
        "poses": [[float(x), float(y), float(a)] for (x, y), a in zip(xy, yaw, strict=True)],
        "fz_n": [float(v) for v in fz],
        "tilt_x_deg": [float(v) for v in np.rad2deg(tx)],
        "tilt_y_deg": [float(v) for v in np.rad2deg(ty)],
        "blurred": [int(i) for i in np.flatnonzero(blurred_flags)],
        "blur_px": [int(v) for v in blur_px],
        "gains": [float(v) for v in gains],
        "imaging": look.to_dict(),
        "path_length_mm": path_length_mm(xy),
        "force_offsets_n": [float(v) for v in offsets],
        "tissue": law.to_dict(),
        "texture": "procedural" if texture is None else "photograph",
    }
    if law.anisotropy_axis == "tissue":  # the axis in frame 0's axes (the path's and the mosaic's)
        truth["anisotropy_angle_frame0_deg"] = law.anisotropy_angle_deg - float(motion.yaw_deg[0])
    if skin_drag is not None:
        truth.update(drag=skin_drag.to_dict(), drag_mm=[[float(x), float(y)] for x, y in drags])
    if in_air is not None:
        truth.update(
            in_air=[int(i) for i in np.flatnonzero(in_air)],
            dropped=[int(i) for i in np.flatnonzero(dropped)],
            clock_skew_s=skew,
            path_length_mm=stroke_length_mm(motion.centre_mm, in_air),
        )
    return Scan(
        calibration=calib,
        frame_seq=kept.astype(np.int64),
        frame_t_s=np.asarray(motion.frame_t_s, dtype=np.float64)[kept],
        force_t_s=force_t + skew,
        forces_n=forces,
        frame_loader=in_memory_loader([frames[k] for k in kept]),
        mask=geometry.mask.copy(),
        imu_t_s=imu_t if with_imu else None,
        imu_tilt_deg=imu_deg if with_imu else None,
        reference_mm=xy[kept].copy(),
        reference_angles_deg=angles_deg[kept],
        truth=truth,
    )
