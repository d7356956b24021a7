"""First guesses of the two periods from the spectrum of the training data."""

from __future__ import annotations

import itertools

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]


def _fft_peaks(t: Array, y: Array, count: int) -> list[tuple[float, float]]:
    """The ``count`` strongest local maxima (frequency Hz, magnitude) of a Hann-windowed,
    16x zero-padded FFT of one mean-removed series; the padding refines each peak's frequency
    beyond the ``1/T`` bin of the plain FFT of Algorithm 1."""
    dt = float(np.median(np.diff(t)))
    grid = np.arange(t[0], t[-1] + 0.5 * dt, dt)
    if len(grid) != len(t) or not np.allclose(grid, t, atol=1e-6 * dt):
        y = np.interp(grid, t, y)  # missed frames: the FFT needs a uniform grid
    yc = (y - y.mean()) * np.hanning(len(y))
    nfft = 16 * int(2 ** np.ceil(np.log2(len(y))))
    spec = np.abs(np.fft.rfft(yc, n=nfft))
    freq = np.fft.rfftfreq(nfft, dt)
    inner = (spec[1:-1] > spec[:-2]) & (spec[1:-1] >= spec[2:])
    idx = np.nonzero(inner)[0] + 1
    idx = idx[freq[idx] > 0.0]
    idx = idx[np.argsort(spec[idx])[::-1][:count]]
    return [(float(freq[i]), float(spec[i])) for i in idx]


def fft_period_guess(t: ArrayLike, Y: ArrayLike, peaks: int = 2) -> list[tuple[float, float]]:
    """Kabir 2025 Algorithm 1: candidate period pairs ``(P1, P2)`` (s), best first.

    For every output the ``peaks`` strongest FFT peaks give periods; each pair of distinct
    periods is scored by ``|P_a - P_b|`` times the sum of their magnitudes (steps 6-10), and
    the pairs are returned in decreasing score (the first is Algorithm 1's choice).
    """
    t, Y = np.asarray(t, float), np.atleast_2d(np.asarray(Y, float).T).T
    found: dict[float, float] = {}
    for j in range(Y.shape[1]):
        for f, mag in _fft_peaks(t, Y[:, j], peaks):
            P = 1.0 / f
            # "unique periods" (step 6): peaks of different outputs within 2% are one period
            key = next((k for k in found if abs(k - P) <= 0.02 * P), None)
            if key is None:
                found[P] = mag
            else:
                found[key] = max(found[key], mag)
    pairs = []
    for (Pa, ma), (Pb, mb) in itertools.combinations(found.items(), 2):
        pairs.append((abs(Pa - Pb) * (ma + mb), (max(Pa, Pb), min(Pa, Pb))))
    pairs.sort(key=lambda p: -p[0])
    return [p for _, p in pairs]
