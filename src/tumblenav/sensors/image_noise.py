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

Speed (tumblenav default, same statistics as the per-pixel chain)
-----------------------------------------------------------------
Only the pixels that receive signal (``s > 0`` after the blur; the caller may name a box
``support`` outside which its signal is zero) go through the per-pixel chain above, with one
``float32`` Gaussian draw per pixel: in the Gaussian limit the shot and read noise are one
Gaussian of variance ``e + dark + read^2`` (their sum, exactly), below it a Poisson draw plus
the read noise.  Every other pixel (black space, shadows outside the target, eclipse frames)
has the same DN distribution, that of dark current plus read noise, whose 256 probabilities
are computed once (:func:`background_pmf`): the frame is drawn from them directly, as the
few non-zero outcomes only when zero is likely (``P(DN > 0) <= _SPARSE_BELOW``: the gaps
between non-zero pixels are geometric, their values drawn from the pmf given DN > 0, which
gives each pixel the pmf independently) and by inverse CDF otherwise.  The pixels' marginal
distributions and their independence are those of the per-pixel chain (up to ``float32``
rounding at the rounding boundaries); the draws, so the pixels of a given seed, differ from
the chain's.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import cv2
import numpy as np
from numpy.typing import NDArray
from scipy import special, stats

from tumblenav.errors import InputError

__all__ = ["DefectPattern", "ImageNoise", "apply_noise", "background_pmf", "defect_pattern"]

F32 = NDArray[np.float32]
_GAUSS_ABOVE_E = 50.0
_SPARSE_BELOW = 0.2  # P(DN > 0) of a dark pixel below which only non-zero DN are drawn


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


Box = tuple[int, int, int, int]  # rows [j0, j1), columns [i0, i1)


@lru_cache(maxsize=32)
def background_pmf(noise: ImageNoise) -> NDArray[np.float64]:
    """Probabilities of DN 0..255 of a pixel without signal: dark electrons (Poisson, exact
    below ``_GAUSS_ABOVE_E`` with shot noise on, its Gaussian limit above, as the chain draws
    them) plus Gaussian read noise, quantised and clipped as in :func:`apply_noise`."""
    c = 255.0 / noise.full_well_e  # DN per electron
    lam, sig = float(noise.dark_current_e), float(noise.read_noise_e)
    pmf = np.zeros(256)
    gauss_dark = noise.shot and lam >= _GAUSS_ABOVE_E
    if lam > 0 and not gauss_dark:  # Poisson dark electrons k with weights w
        spread = 12.0 * np.sqrt(lam) + 30.0  # the Poisson mass beyond is below 1e-30
        k = np.arange(max(int(lam - spread), 0), int(lam + spread), dtype=float)
        w = stats.poisson.pmf(k, lam)
        if sig == 0:  # DN a function of k, as the chain computes it (float32)
            dn = np.clip(np.rint(k.astype(np.float32) * np.float32(c)), 0, 255).astype(int)
            np.add.at(pmf, dn, w)
            return pmf / pmf.sum()
    else:
        k, w = np.zeros(1), np.ones(1)
    mean = lam if gauss_dark else 0.0
    sd = np.sqrt(sig**2 + (lam if gauss_dark else 0.0))
    if sd == 0:
        pmf[0] = 1.0
        return pmf
    # P(DN >= d) = P(e >= (d - 1/2) / c) for d = 1..255 (survival function: accurate tails)
    edges = (np.arange(1, 256) - 0.5) / c
    sf = (w[None, :] * special.ndtr((mean + k[None, :] - edges[:, None]) / sd)).sum(axis=1)
    sf = np.concatenate([[1.0], sf, [0.0]])
    pmf = np.maximum(sf[:-1] - sf[1:], 0.0)
    return pmf / pmf.sum()


def _background(noise: ImageNoise, out: NDArray[np.uint8], rng: np.random.Generator) -> None:
    """Fill ``out`` (flat) with independent DN of pixels without signal, drawn from
    :func:`background_pmf`."""
    pmf = background_pmf(noise)
    p_on = 1.0 - pmf[0]
    n = out.size
    if p_on <= 0.0:
        out[:] = 0
        return
    if p_on > _SPARSE_BELOW:  # inverse CDF, one uniform a pixel
        cdf = np.cumsum(pmf).astype(np.float32)
        cdf[-1] = np.float32(np.inf)
        u = rng.random(n, dtype=np.float32)
        out[:] = np.searchsorted(cdf, u, side="right")
        return
    # mostly zeros: each pixel is non-zero with probability p_on, independently, so the gaps
    # between successive non-zero pixels are geometric
    out[:] = 0
    mean = n * p_on
    m = int(mean + 6.0 * np.sqrt(mean) + 16.0)
    pos = np.cumsum(rng.geometric(p_on, size=m)) - 1
    while pos[-1] < n:  # more than 6 sigma of non-zero pixels: draw on
        pos = np.concatenate([pos, pos[-1] + np.cumsum(rng.geometric(p_on, size=m))])
    pos = pos[pos < n]
    cdf_on = np.cumsum(pmf[1:]) / p_on  # DN 1..255 given DN > 0
    cdf_on[-1] = np.inf
    out[pos] = np.searchsorted(cdf_on, rng.random(pos.size), side="right") + 1


def _signal_box(s: F32) -> Box:
    """The smallest box holding every non-zero pixel of ``s`` (empty: (0, 0, 0, 0))."""
    rows = np.flatnonzero(s.any(axis=1))
    if rows.size == 0:
        return 0, 0, 0, 0
    cols = np.flatnonzero(s[rows[0] : rows[-1] + 1].any(axis=0))
    return int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1


def _blur(s: F32, sigma: float, box: Box) -> tuple[F32, Box]:
    """Gaussian PSF (reflected borders) of ``s``, zero outside ``box``; computed on the box
    grown by twice the kernel radius (the same values as on the whole frame: the reflected
    border there reads zeros), returns the blurred frame and its non-zero box."""
    h, w = s.shape
    j0, j1, i0, i1 = box
    out = np.zeros_like(s)
    if j1 <= j0 or i1 <= i0:
        return out, box
    r = int(np.ceil(4.0 * sigma)) + 1  # >= OpenCV's radius, cvRound(8 sigma + 1) // 2
    a0, a1, b0, b1 = max(j0 - 2 * r, 0), min(j1 + 2 * r, h), max(i0 - 2 * r, 0), min(i1 + 2 * r, w)
    win = cv2.GaussianBlur(
        np.ascontiguousarray(s[a0:a1, b0:b1]), (0, 0), sigma, borderType=cv2.BORDER_REFLECT
    )
    out[a0:a1, b0:b1] = win
    return out, (max(j0 - r, 0), min(j1 + r, h), max(i0 - r, 0), min(i1 + r, w))


def _signal_electrons(lam: F32, e: F32, noise: ImageNoise, rng: np.random.Generator) -> F32:
    """Noisy electrons of the pixels with signal: ``e`` signal electrons, ``lam = e + dark``;
    one standard-normal draw per pixel (shot and read noise summed in the Gaussian limit)."""
    read = np.float32(noise.read_noise_e)
    z = rng.standard_normal(lam.size, dtype=np.float32)
    if not noise.shot:
        out = e.copy()
        if noise.dark_current_e > 0:
            out += rng.poisson(noise.dark_current_e, size=lam.size).astype(np.float32)
        return out + read * z
    out = lam + np.sqrt(lam + read * read) * z  # Gaussian limit: shot + read in one draw
    small = np.flatnonzero(lam < _GAUSS_ABOVE_E)
    if small.size:
        exact = rng.poisson(lam[small]).astype(np.float32)
        out[small] = exact + read * z[small]
    return out


def apply_noise(
    signal: F32,
    noise: ImageNoise | None,
    rng: np.random.Generator | None,
    defects: DefectPattern | None = None,
    support: Box | None = None,
) -> NDArray[np.uint8]:
    """Turn an image level map ``signal`` (H, W; fraction of full scale, >= 0) into 8-bit DN.

    ``noise=None`` quantises only.  ``rng`` is used only when ``noise.random``; ``defects``
    (from :func:`defect_pattern`) may be None when there are none.  ``support`` (rows
    ``[j0, j1)``, columns ``[i0, i1)``): the caller's promise that ``signal`` is zero outside
    that box (None: found here).
    """
    s = np.asarray(signal, dtype=np.float32)
    if s.ndim != 2:
        raise InputError(f"signal must be a 2-D image, got shape {s.shape}")
    h, w = s.shape
    box = _signal_box(s) if support is None else support
    j0, j1, i0, i1 = box = (max(box[0], 0), min(box[1], h), max(box[2], 0), min(box[3], w))
    if noise is not None and noise.blur_sigma_px > 0:
        s, box = _blur(s, noise.blur_sigma_px, box)
        j0, j1, i0, i1 = box
    dn = np.zeros((h, w), np.uint8)
    if noise is None or not noise.random:
        full = 255.0 if noise is None else noise.full_well_e
        e = s[j0:j1, i0:i1] * np.float32(full)
        q = np.rint(e * np.float32(255.0 / full))
        dn[j0:j1, i0:i1] = np.clip(q, 0, 255).astype(np.uint8)
    else:
        if rng is None:
            raise InputError("this image noise needs a random generator")
        flat = dn.reshape(-1)
        _background(noise, flat, rng)
        if j1 > j0 and i1 > i0:
            sub = s[j0:j1, i0:i1]
            rr, cc = np.nonzero(sub > 0)
            idx = (rr + j0) * w + (cc + i0)
            e = sub[rr, cc] * np.float32(noise.full_well_e)
            lam = e + np.float32(noise.dark_current_e)
            out = _signal_electrons(lam, e, noise, rng)
            q = np.rint(out * np.float32(255.0 / noise.full_well_e))
            flat[idx] = np.clip(q, 0, 255).astype(np.uint8)
    if defects is not None:
        flat = dn.reshape(-1)
        flat[defects.dead] = 0
        flat[defects.hot] = 255
    return dn
