"""Image-sensor noise chain for rendered frames: optics blur, photon and dark shot noise, read
noise, dead/hot pixels, 8-bit quantisation.

Chang 2021 adds no image noise to its Unity renders (Sec. 3.2 is silent); every value here is a
``# tumblenav default (Chang 2021 silent)``.  The steps follow the signal through a camera,
each optional (its "off" value in brackets) and seeded by the caller's generator:

1. optics: Gaussian PSF of ``blur_sigma_px`` [0] on the irradiance image (mean conserving,
   reflected borders);
2. detection: electrons ``e = s * full_well_e`` for an image level ``s`` (fraction of full
   scale); dark current ``dark_current_e`` [0] adds mean electrons; photon and dark shot noise
   are Poisson on their sum (``shot`` [on]; with ``shot`` off the dark electrons are still
   Poisson) -- drawn exactly below ``_GAUSS_ABOVE_E`` electrons and by its Gaussian limit
   (same mean and variance) above, 4x faster on a 1024^2 frame;
3. read noise: Gaussian, ``read_noise_e`` [0] electrons rms;
4. defects: dead pixels read 0, hot pixels saturate (``dead_pixel_fraction``,
   ``hot_pixel_fraction`` [0]); their positions are a fixed pattern of the camera, drawn from
   ``(defect_seed, camera index)``, never redrawn per frame;
5. quantisation to 8 bits: ``DN = round(255 e / full_well_e)``, clipped to ``[0, 255]``.

The steps are the ones of Basilisk's ``camera`` module (Gaussian noise, blur, dark current,
dead/stuck pixels), in the order of the physics.  With every step off no random number is drawn.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

from tumblenav.errors import InputError

__all__ = ["DefectPattern", "ImageNoise", "apply_noise", "defect_pattern"]

F32 = NDArray[np.float32]
_GAUSS_ABOVE_E = 50.0


@dataclass(frozen=True)
class ImageNoise:
    """Image-noise settings (electrons; pixels); every field has an "off" value.

    Attributes
    ----------
    full_well_e : float
        Electrons at 8-bit full scale (255 DN); sets the shot-noise level.
    shot : bool
        Photon shot noise (Poisson on the signal electrons).
    read_noise_e : float
        Read noise, Gaussian, electrons rms (0 = off).
    dark_current_e : float
        Mean dark electrons per frame, Poisson (0 = off).
    blur_sigma_px : float
        Standard deviation of the Gaussian PSF (px) (0 = off).
    dead_pixel_fraction, hot_pixel_fraction : float
        Fractions of pixels that read 0 / saturate (0 = off).
    defect_seed : int
        Seed of the dead/hot pixel pattern (fixed per camera, not per frame).
    """

    full_well_e: float = 20000.0
    shot: bool = True
    read_noise_e: float = 0.0
    dark_current_e: float = 0.0
    blur_sigma_px: float = 0.0
    dead_pixel_fraction: float = 0.0
    hot_pixel_fraction: float = 0.0
    defect_seed: int = 0

    def __post_init__(self) -> None:
        if not self.full_well_e > 0:
            raise InputError(f"full_well_e must be positive, got {self.full_well_e}")
        for name in ("read_noise_e", "dark_current_e", "blur_sigma_px"):
            if not getattr(self, name) >= 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        for name in ("dead_pixel_fraction", "hot_pixel_fraction"):
            if not 0 <= getattr(self, name) <= 1:
                raise InputError(f"{name} must be in [0, 1], got {getattr(self, name)}")
        if self.dead_pixel_fraction + self.hot_pixel_fraction > 1:
            raise InputError("dead_pixel_fraction + hot_pixel_fraction must not exceed 1")

    @property
    def random(self) -> bool:
        """True if a frame draws random numbers (shot, read or dark noise)."""
        return self.shot or self.read_noise_e > 0 or self.dark_current_e > 0


@dataclass(frozen=True, eq=False)
class DefectPattern:
    """Flat indices of a camera's dead and hot pixels."""

    dead: NDArray[np.int64]
    hot: NDArray[np.int64]


def defect_pattern(noise: ImageNoise, shape: tuple[int, int], camera: int) -> DefectPattern:
    """The fixed dead/hot pixel pattern of camera ``camera`` (0 left, 1 right) of size
    ``shape = (H, W)``: the same for the same ``noise.defect_seed``, whatever the frame."""
    n = shape[0] * shape[1]
    n_dead = int(round(noise.dead_pixel_fraction * n))
    n_hot = int(round(noise.hot_pixel_fraction * n))
    if n_dead + n_hot == 0:
        empty = np.zeros(0, np.int64)
        return DefectPattern(empty, empty)
    rng = np.random.default_rng([noise.defect_seed, camera, 0xDEAD])
    idx = rng.choice(n, size=n_dead + n_hot, replace=False).astype(np.int64)
    return DefectPattern(np.sort(idx[:n_dead]), np.sort(idx[n_dead:]))


def _poisson(lam: F32, rng: np.random.Generator) -> F32:
    """Poisson draws of mean ``lam`` (float32): exact below ``_GAUSS_ABOVE_E``, Gaussian limit
    (mean and variance ``lam``) above; zero where ``lam == 0`` (no draw)."""
    out = lam.copy()
    flat_lam, flat_out = lam.ravel(), out.ravel()
    small = np.flatnonzero((flat_lam > 0) & (flat_lam < _GAUSS_ABOVE_E))
    large = np.flatnonzero(flat_lam >= _GAUSS_ABOVE_E)
    if small.size:
        flat_out[small] = rng.poisson(flat_lam[small]).astype(np.float32)
    if large.size:
        z = rng.standard_normal(large.size, dtype=np.float32)
        flat_out[large] += np.sqrt(flat_lam[large]) * z
    return out


def apply_noise(
    signal: F32,
    noise: ImageNoise | None,
    rng: np.random.Generator | None,
    defects: DefectPattern | None = None,
) -> NDArray[np.uint8]:
    """Turn an image level map ``signal`` (H, W; fraction of full scale, >= 0) into 8-bit DN.

    ``noise=None`` quantises only.  ``rng`` is used only when ``noise.random``; ``defects``
    (from :func:`defect_pattern`) may be None when there are none.
    """
    s = np.asarray(signal, dtype=np.float32)
    if noise is None:
        return np.clip(np.rint(s * 255.0), 0, 255).astype(np.uint8)
    if noise.blur_sigma_px > 0:
        blurred = cv2.GaussianBlur(s, (0, 0), noise.blur_sigma_px, borderType=cv2.BORDER_REFLECT)
        s = np.asarray(blurred, np.float32)
    e = s * np.float32(noise.full_well_e)
    if noise.random:
        if rng is None:
            raise InputError("this image noise needs a random generator")
        if noise.shot:
            e = _poisson(e + np.float32(noise.dark_current_e), rng)
        elif noise.dark_current_e > 0:
            e = e + np.asarray(rng.poisson(noise.dark_current_e, size=e.shape), np.float32)
        if noise.read_noise_e > 0:
            e = e + np.float32(noise.read_noise_e) * rng.standard_normal(e.shape, np.float32)
    dn = np.clip(np.rint(e * np.float32(255.0 / noise.full_well_e)), 0, 255).astype(np.uint8)
    if defects is not None:
        flat = dn.reshape(-1)
        flat[defects.dead] = 0
        flat[defects.hot] = 255
    return dn
