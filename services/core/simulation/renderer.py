"""Rendering a simulated frame: the true skin deformation (close to spec §2) and the probe's imaging chain."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from services.core.inputs.calibration import Calibration
from services.core.physics.camera import px_to_mm, undistort_points_px
from services.core.physics.force_model import LoadState, local_load_n
from services.core.physics.rectification import pixel_grid
from services.core.simulation.probe_path import rotation
from services.core.simulation.skin_drag import SkinDrag, dragged_rest_mm
from services.core.simulation.vein_texture import World

UNMODELLED_RADIAL = 0.05  # the true stretch grows by this fraction at |p'| = UNMODELLED_RADIUS_MM (not in §2)
UNMODELLED_RADIUS_MM = 25.0
WINDOW_SIZE_PX = (624.0, 464.0)  # the window almost fills the 640 x 480 frame (as on the shared scans' mask)
WINDOW_CORNER_RADIUS_PX = 40.0
DARK_LEVEL = 1.5 / 255.0  # outside the window: ~1.5 DN (8-bit) plus noise, as on the shared scans
VIGNETTE_FALLOFF = 0.12  # illumination drops by this fraction at the window's edge (0.88; corners ~0.77)
FULL_SCALE_DN = 255.0  # noise is given in 8-bit grey levels (DN) whatever the output bit depth


TISSUE_LAWS = ("linear", "stiffening", "power", "toe", "saturating")
ANISOTROPY_AXES = ("probe", "tissue")


@dataclass(frozen=True)
class TissueLaw:
    """The simulated tissue's true response: strain of local load F (N) and its x/y anisotropy.

    linear: c F (spec §2's shape); the others have the secant compliance c at the anchor load F0 (the scan's
    typical load: the calibration's E is a secant measured at the loads a normal press uses, spec §2 Calibration):
    stiffening: c F (1 + F0 / half_n) / (1 + F / half_n) (strain saturates as tissue stiffens); power:
    c F0 (F / F0)^exponent (flatter above F0); toe: Fung's exponential stress-strain law, strain logarithmic in
    load, c F0 ln(1 + F / toe_n) / ln(1 + F0 / toe_n) (a soft toe region below toe_n); saturating:
    c F0 (1 - exp(-F / sat_n)) / (1 - exp(-F0 / sat_n)) (the strain levels off above sat_n).

    Anisotropy: the strain is (1 + anisotropy) times it along an axis and (1 - anisotropy) across it. The axis is
    at anisotropy_angle_deg from the frame's x axis when anisotropy_axis is "probe" (it turns with the probe), or
    from the world's x axis when "tissue" (fixed in the tissue: in the frame it turns against the probe's yaw).
    """

    kind: str = "linear"
    compliance_per_n: float = 0.0
    half_n: float = 40.0
    exponent: float = 0.8
    anisotropy: float = 0.0
    toe_n: float = 15.0
    sat_n: float = 6.0
    anisotropy_axis: str = "probe"
    anisotropy_angle_deg: float = 0.0
    anchor_n: float = 10.0
    # the strain's growth towards the rim, not in spec §2: (1 + radial (|p'| / UNMODELLED_RADIUS_MM)^2) times it
    radial: float = UNMODELLED_RADIAL

    def strain(self, load_n: np.ndarray) -> np.ndarray:
        """Return the isotropic strain (dimensionless) at local loads (N)."""
        f = np.maximum(np.asarray(load_n, np.float64), 0.0)
        f0, c = self.anchor_n, self.compliance_per_n
        if self.kind == "stiffening":
            return c * f * (1.0 + f0 / self.half_n) / (1.0 + f / self.half_n)
        if self.kind == "power":
            return c * f0 * (f / f0) ** self.exponent
        if self.kind == "toe":
            return c * f0 * np.log1p(f / self.toe_n) / np.log1p(f0 / self.toe_n)
        if self.kind == "saturating":
            return c * f0 * -np.expm1(-f / self.sat_n) / -np.expm1(-f0 / self.sat_n)
        return c * f

    def anisotropy_tensor(self, yaw_deg: float) -> np.ndarray:
        """Return (2, 2) I + anisotropy Q in the frame's axes at a probe yaw (deg): the strain's relative stretch,
        Q the traceless symmetric tensor of the axis (cos 2a, sin 2a; sin 2a, -cos 2a)."""
        angle = self.anisotropy_angle_deg - (yaw_deg if self.anisotropy_axis == "tissue" else 0.0)
        c, s = np.cos(np.radians(2.0 * angle)), np.sin(np.radians(2.0 * angle))
        return np.eye(2) + self.anisotropy * np.array([[c, s], [s, -c]])

    def to_dict(self) -> dict[str, float | str]:
        """Return the law's truth (truth.json; TissueLaw(**d) of it is the law again)."""
        return {
            "kind": self.kind,
            "compliance_per_n": self.compliance_per_n,
            "half_n": self.half_n,
            "exponent": self.exponent,
            "anisotropy": self.anisotropy,
            "toe_n": self.toe_n,
            "sat_n": self.sat_n,
            "anisotropy_axis": self.anisotropy_axis,
            "anisotropy_angle_deg": self.anisotropy_angle_deg,
            "anchor_n": self.anchor_n,
            "radial": self.radial,
        }


def view_stretch(observed_mm: np.ndarray, state: LoadState) -> np.ndarray:
    """Return surface mm (..., 2) of observed mm under a tilted view: 1/cos(tilt) along the tilt, undone.

    The view of a probe tilted by theta is the surface stretched 1/cos(theta) along the tilt direction (the
    image-plane part of the tilted normal), as the paper models it and as the shared scans show.
    """
    n = state.normal
    g = np.array([n[0], n[1]])
    norm = float(np.linalg.norm(g))
    if norm < 1e-12:
        return observed_mm
    g /= norm
    along = observed_mm @ g
    return observed_mm + ((float(n[2]) - 1.0) * along)[..., None] * g


@dataclass(frozen=True)
class FrameGeometry:
    """Per-scan precomputations: observed mm (H, W, 2) of every raw pixel, window mask, alpha and vignette."""

    observed_mm: np.ndarray  # float64 (H, W, 2): undistorted position of each raw pixel, mm about (cx, cy)
    radius_sq_mm2: np.ndarray  # float64 (H, W): |observed_mm|^2
    mask: np.ndarray  # uint8 (H, W) 0/255: inside the window
    alpha: np.ndarray  # float32 (H, W) in [0, 1]: the window with a one-pixel soft edge
    vignette: np.ndarray  # float32 (H, W): IR-ring illumination gain


@dataclass(frozen=True)
class Imaging:
    """Per-frame imaging: sensor noise std in 8-bit grey levels (DN), exposure gain, blur, output dtype."""

    noise_dn: float = 2.0
    gain: float = 1.0
    blur_kernel: np.ndarray | None = None
    dtype: type = np.uint8


def window_centre_px(calib: Calibration) -> tuple[float, float]:
    """Return the window's centre (px): the image centre (the window is part of the probe, not of the lens)."""
    w, h = calib.image_size
    return (w - 1) / 2.0, (h - 1) / 2.0


def window_signed_distance(calib: Calibration) -> np.ndarray:
    """Return the signed distance (px, negative inside) of every pixel to the rounded-rectangle window."""
    w, h = calib.image_size
    grid = pixel_grid(w, h)
    cx, cy = window_centre_px(calib)
    half = np.array(WINDOW_SIZE_PX) / 2.0 - WINDOW_CORNER_RADIUS_PX
    q = np.abs(grid - (cx, cy)) - half
    outside = np.linalg.norm(np.maximum(q, 0.0), axis=-1)
    inside = np.minimum(np.max(q, axis=-1), 0.0)
    return outside + inside - WINDOW_CORNER_RADIUS_PX


def vignette_gain(calib: Calibration) -> np.ndarray:
    """Return the IR-ring illumination gain (float32, H x W): 1 at the centre, ~0.88 at the window's edges and
    ~0.77 in its corners (the profile measured on the shared scans), with a slight left-right imbalance."""
    w, h = calib.image_size
    grid = pixel_grid(w, h)
    d = (grid - window_centre_px(calib)) / (np.array(WINDOW_SIZE_PX) / 2.0)
    rn2 = np.sum(d * d, axis=-1)  # 0 at the centre, 1 at the middle of the window's edges
    tilt = 1.0 + 0.02 * d[..., 0] - 0.01 * d[..., 1]  # the LEDs are not perfectly even
    return ((1.0 - VIGNETTE_FALLOFF * rn2) * tilt).astype(np.float32)


def frame_geometry(calib: Calibration) -> FrameGeometry:
    """Return the FrameGeometry of a calibration (undistortion done once per scan)."""
    w, h = calib.image_size
    ideal = undistort_points_px(pixel_grid(w, h).reshape(-1, 2), calib).reshape(h, w, 2)
    obs = px_to_mm(ideal, calib)
    sd = window_signed_distance(calib)
    mask = np.where(sd <= 0.0, 255, 0).astype(np.uint8)
    alpha = np.clip(0.5 - sd, 0.0, 1.0).astype(np.float32)
    return FrameGeometry(obs, np.sum(obs * obs, axis=-1), mask, alpha, vignette_gain(calib))


def true_undeformed_mm(
    geometry: FrameGeometry,
    state: LoadState,
    true_calib: Calibration,
    law: TissueLaw | None = None,
    yaw_deg: float = 0.0,
) -> np.ndarray:
    """Return the undeformed position (H, W, 2) mm about the frame centre of every raw pixel.

    The tilted view is undone first (view_stretch), then p = (I - s(F(p')) (1 + r (|p'| / 25 mm)^2) T) p',
    s the tissue law's strain, T its anisotropy in the frame's axes at the probe's yaw (deg; TissueLaw.
    anisotropy_tensor) and F(p') = max(0, F_Z + kappa Z(p')) from spec §2 with the TRUE constants; the radial term
    (r the law's radial, UNMODELLED_RADIAL by default) is deliberately not in spec §2. Without a law: linear, s = c F
    with c = nu / (E A) of true_calib.
    """
    law = law or TissueLaw("linear", true_calib.compliance_per_n)
    surface = view_stretch(geometry.observed_mm, state)
    load = local_load_n(geometry.observed_mm, state, true_calib)
    extra = 1.0 + law.radial * geometry.radius_sq_mm2 / UNMODELLED_RADIUS_MM**2
    strain = law.strain(load) * extra
    if law.anisotropy == 0.0:
        return surface * (1.0 - strain)[..., None]
    stretched = surface @ law.anisotropy_tensor(yaw_deg).T
    return surface - strain[..., None] * stretched


def world_maps(
    undeformed_mm: np.ndarray, world: World, centre_mm: np.ndarray, yaw_deg: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return cv2.remap maps (float32 x, y) into the world image for frame points (H, W, 2) mm at a pose."""
    r = rotation(yaw_deg)
    world_mm = undeformed_mm @ r.T + np.asarray(centre_mm, dtype=np.float64)
    px = world.mm_to_px(world_mm)
    return px[..., 0].astype(np.float32), px[..., 1].astype(np.float32)


def render_scene(
    world: World,
    geometry: FrameGeometry,
    centre_mm: np.ndarray,
    yaw_deg: float,
    state: LoadState,
    true_calib: Calibration,
    law: TissueLaw | None = None,
    drag: tuple[SkinDrag, np.ndarray] | None = None,
) -> np.ndarray:
    """Return the noiseless deformed view (float32 H x W, reflectance 0..1) seen through the lens.

    drag: the scan's skin drag and this frame's drag at the centre (2,) mm in its axes (skin_drag), or None.
    """
    undeformed = true_undeformed_mm(geometry, state, true_calib, law, yaw_deg)
    if drag is not None:
        undeformed = dragged_rest_mm(undeformed, *drag)
    map_x, map_y = world_maps(undeformed, world, centre_mm, yaw_deg)
    return cv2.remap(world.image, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REFLECT)


def motion_blur_kernel(length_px: int, angle_deg: float) -> np.ndarray:
    """Return a normalised directional blur kernel (float32, odd size) of length_px at angle_deg."""
    size = int(length_px) | 1
    k = np.zeros((size * 4, size * 4), np.uint8)
    c = (size * 4 - 1) / 2.0
    a = np.deg2rad(angle_deg)
    half = (length_px - 1) / 2.0 * 4
    p = (round((c - half * np.cos(a)) * 16), round((c - half * np.sin(a)) * 16))
    q = (round((c + half * np.cos(a)) * 16), round((c + half * np.sin(a)) * 16))
    cv2.line(k, p, q, 255, 4, cv2.LINE_AA, 4)
    kernel = cv2.resize(k.astype(np.float32), (size, size), interpolation=cv2.INTER_AREA)
    return kernel / kernel.sum()


def apply_imaging(scene: np.ndarray, geometry: FrameGeometry, imaging: Imaging, rng: np.random.Generator) -> np.ndarray:
    """Return the recorded frame (uint8 or uint16, H x W): blur, vignetting, window, noise, quantisation."""
    img = scene
    if imaging.blur_kernel is not None:
        img = cv2.filter2D(img, -1, imaging.blur_kernel, borderType=cv2.BORDER_REFLECT)
    img = img * geometry.vignette * np.float32(imaging.gain)
    img = geometry.alpha * img + (1.0 - geometry.alpha) * np.float32(DARK_LEVEL)
    img = img + rng.standard_normal(img.shape, dtype=np.float32) * np.float32(imaging.noise_dn / FULL_SCALE_DN)
    top = float(np.iinfo(imaging.dtype).max)
    return np.clip(np.round(img * top), 0, top).astype(imaging.dtype)
