"""Two batched alternatives to the image front end's per-feature ECC refinement
(src/tumblenav/frontends/stereo_images/refine.py), tried and not kept (sixteenth session,
issue 18): an inverse-compositional Gauss-Newton (Baker & Matthews 2004) with step halving
(``ic``) and a forward-additive one with ECC's gradient and stopping rule (``fa``), both over
all the features with one ``cv2.remap`` per iteration. Run the front-end benchmark with one of
them in place of ``cv2.findTransformECC``::

    python chang_batched_refine.py ic --pairs 130 --ranges-m 9 --timing-pairs 100
    python chang_batched_refine.py fa --pairs 130 --ranges-m 9 --timing-pairs 100
    python ../../../../benchmarks/image_frontend.py --pairs 130 --ranges-m 9 --timing-pairs 100

Measured (the sixteenth session, one idle core): ECC 49.5 ms per pair, drift at 60 frames
0.05 px, mean track 19.5 frames; ``ic`` 44.6 ms, 0.07 px but 0.13 px at ages 2-30 and tracks of
17.1 frames (the template's central differences are not the bilinear image's gradient at a
sharp edge); ``fa`` 66.0 ms, 0.07 px, 20.2 frames.
"""

import runpy
import sys
from pathlib import Path

import cv2
import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.stereo_images.refine import AffineRefinement

Array = NDArray[np.float64]


def refine_ic(
    templates: NDArray[np.float32],
    image: NDArray[np.uint8],
    uv_pred: Array,
    lin: Array,
    min_cc: float,
    max_shift_px: float,
    iterations: int = 20,
) -> AffineRefinement:
    """Warp each template into ``image`` by the affine map of linear part ``lin`` (m, 2, 2)
    that takes the template's centre to ``uv_pred`` (m, 2, tumblenav), refine the six
    parameters to the best correlation, and accept the result when it converges within
    ``iterations``, scores (the correlation coefficient) at least ``min_cc``, stays inside the
    image and moves the centre by at most ``max_shift_px`` from ``uv_pred`` (else ``uv_pred``
    and ``lin`` are returned).

    The alignment is the inverse-compositional Gauss-Newton of Baker & Matthews (2004) with the
    warped patch normalised to the template's mean and standard deviation at each iteration,
    so that it maximises the correlation coefficient as ECC does (Evangelidis & Psarakis 2008;
    ``cv2.findTransformECC`` gives the same warps to ~0.01 px, tests/test_image_frontend.py).
    Written here rather than calling OpenCV because ECC takes one template per call: batched
    over the features (one ``cv2.remap`` per iteration for all of them) the refinement costs
    ~1/10 of the per-feature calls."""
    m = len(uv_pred)
    uv = np.array(uv_pred, float, copy=True)
    lin_out = np.array(lin, float, copy=True)
    cc = np.full(m, np.nan)
    ok = np.zeros(m, bool)
    live = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
    if not live.size:
        return AffineRefinement(uv, lin_out, cc, ok)
    side = templates.shape[-1]
    c = (side - 1) / 2.0
    g = np.arange(side, dtype=float) - c
    gx, gy = np.meshgrid(g, g)  # template coordinates of each pixel (x right, y down)
    xs, ys = gx.ravel(), gy.ravel()
    T = templates[live].reshape(len(live), -1).astype(float)  # (n, s^2)
    Tm = T.mean(axis=1, keepdims=True)
    Ts = T.std(axis=1, keepdims=True)
    Tz = T - Tm
    dTy, dTx = np.gradient(templates[live].astype(float), axis=(1, 2))
    dTx, dTy = dTx.reshape(len(live), -1), dTy.reshape(len(live), -1)
    # steepest-descent images of p = (a11 - 1, a21, a12, a22 - 1, tx, ty) at p = 0
    SD = np.stack([dTx * xs, dTy * xs, dTx * ys, dTy * ys, dTx, dTy], axis=-1)  # (n, s^2, 6)
    # the template's mean and its own direction are projected out: a change of gain or offset
    # is not a move (the correlation coefficient ignores both)
    a2 = Tz / np.maximum(np.linalg.norm(Tz, axis=1, keepdims=True), 1e-12)
    SD = SD - SD.mean(axis=1, keepdims=True)
    SD = SD - a2[:, :, None] * np.einsum("np,npk->nk", a2, SD)[:, None, :]
    Hs = np.einsum("npk,npl->nkl", SD, SD) + 1e-9 * np.eye(6)
    M = np.zeros((len(live), 3, 3))  # template coordinates -> OpenCV pixels of the image
    M[:, :2, :2] = lin[live]
    M[:, :2, 2] = uv[live] - 0.5
    M[:, 2, 2] = 1.0
    img = image.astype(np.float32)
    h, w = image.shape
    act = np.ones(len(live), bool)
    conv = np.zeros(len(live), bool)
    step = np.ones(len(live))  # halved where a step would raise the error (below)
    sse_prev = np.full(len(live), np.inf)
    M_prev = M.copy()
    dp = np.zeros((len(live), 6))
    for _ in range(iterations):
        a = np.flatnonzero(act)
        if not a.size:
            break
        Iw, inside = _warped_ic(img, M[a], xs, ys, w, h)
        mu = Iw.mean(axis=1, keepdims=True)
        sd = np.maximum(Iw.std(axis=1, keepdims=True), 1e-6)
        e = (Iw - mu) * (Ts[a] / sd) - Tz[a]  # the warped patch at the template's mean and sigma
        sse = np.einsum("np,np->n", e, e)
        # a step that raised the error is taken back and halved: the template's central
        # differences are not the gradient of the bilinear image at a sharp edge, and a full
        # Gauss-Newton step there overshoots (up to 2x) and oscillates
        worse = sse > sse_prev[a]
        b = a[worse]
        M[b], step[b] = M_prev[b], 0.5 * step[b]
        g = a[~worse]
        sse_prev[g] = sse[~worse]
        dp[g] = np.linalg.solve(Hs[g], np.einsum("npk,np->nk", SD[g], e[~worse])[..., None])[..., 0]
        upd = a  # every active feature steps: from its new point or, halved, from its last
        d = step[upd, None] * dp[upd]
        D = np.zeros((len(upd), 3, 3))
        D[:, 0, 0], D[:, 1, 0], D[:, 0, 1], D[:, 1, 1] = 1 + d[:, 0], d[:, 1], d[:, 2], 1 + d[:, 3]
        D[:, :2, 2], D[:, 2, 2] = d[:, 4:], 1.0
        M_prev[upd] = M[upd]
        M[upd] = M[upd] @ np.linalg.inv(D)  # inverse composition
        done = np.abs(d[:, 4:]).max(axis=1) < 1e-3
        bad = ~inside | ~np.all(np.isfinite(M[upd]), axis=(1, 2))
        conv[upd[done & ~bad]] = True
        act[upd[done | bad]] = False
    Iw, inside = _warped_ic(img, M, xs, ys, w, h)
    Iz = Iw - Iw.mean(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.einsum("np,np->n", Iz, Tz) / (
            np.linalg.norm(Iz, axis=1) * np.linalg.norm(Tz, axis=1)
        )
    new = M[:, :2, 2] + 0.5
    shift = np.hypot(*(new - uv[live]).T)
    good = conv & inside & (score >= min_cc) & (shift <= max_shift_px)
    cc[live] = score
    uv[live[good]] = new[good]
    lin_out[live[good]] = M[good, :2, :2]
    ok[live[good]] = True
    return AffineRefinement(uv, lin_out, cc, ok)


def _warped_ic(
    img: NDArray[np.float32], M: Array, xs: Array, ys: Array, w: int, h: int
) -> tuple[Array, NDArray[np.bool_]]:
    """The image sampled (bilinear, one ``cv2.remap`` for all) at ``M`` (n, 3, 3) applied to the
    template coordinates (``xs``, ``ys``), (n, s^2), and whether each warped patch lies inside."""
    X = M[:, 0, 0, None] * xs + M[:, 0, 1, None] * ys + M[:, 0, 2, None]
    Y = M[:, 1, 0, None] * xs + M[:, 1, 1, None] * ys + M[:, 1, 2, None]
    inside = np.all((X >= 0) & (X <= w - 1) & (Y >= 0) & (Y <= h - 1), axis=1)
    out = cv2.remap(
        img, X.astype(np.float32), Y.astype(np.float32), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip
    return out.astype(float), inside


def refine_fa(templates, image, uv_pred, lin, min_cc, max_shift_px, iterations=20):
    """Forward-additive Gauss-Newton on the normalised patch (ECC's gradient: Sobel of the
    image, warped with it; ECC's stopping rule: the correlation changes by < 1e-3)."""
    m = len(uv_pred)
    uv = np.array(uv_pred, float, copy=True)
    lin_out = np.array(lin, float, copy=True)
    cc = np.full(m, np.nan)
    ok = np.zeros(m, bool)
    live = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
    if not live.size:
        return AffineRefinement(uv, lin_out, cc, ok)
    side = templates.shape[-1]
    c = (side - 1) / 2.0
    g = np.arange(side, dtype=np.float32) - c
    gx, gy = np.meshgrid(g, g)
    xs, ys = gx.ravel(), gy.ravel()
    T = templates[live].reshape(len(live), -1).astype(np.float32)
    Tz = T - T.mean(axis=1, keepdims=True)
    Tn = Tz / np.maximum(np.linalg.norm(Tz, axis=1, keepdims=True), 1e-6)
    img = image.astype(np.float32)
    stack = cv2.merge(
        [
            img,
            cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125),
            cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125),
        ]
    )
    h, w = image.shape
    M = np.zeros((len(live), 2, 3), np.float32)
    M[:, :, :2] = lin[live]
    M[:, :, 2] = uv[live] - 0.5
    act = np.ones(len(live), bool)
    rho = np.full(len(live), -np.inf)
    for _ in range(iterations):
        a = np.flatnonzero(act)
        if not a.size:
            break
        S, ins = _warped_fa(stack, M[a], xs, ys, w, h)
        I, Gx, Gy = S[..., 0], S[..., 1], S[..., 2]
        J = np.stack([Gx * xs, Gy * xs, Gx * ys, Gy * ys, Gx, Gy], axis=-1)
        J -= J.mean(axis=1, keepdims=True)
        Iz = I - I.mean(axis=1, keepdims=True)
        nI = np.maximum(np.linalg.norm(Iz, axis=1), 1e-6)
        r = np.einsum("np,np->n", Iz, Tn[a]) / nI
        e = Tn[a] - Iz / nI[:, None]
        Jn = J / nI[:, None, None]
        H = np.einsum("npk,npl->nkl", Jn, Jn) + 1e-9 * np.eye(6, dtype=np.float32)
        dp = np.linalg.solve(H, np.einsum("npk,np->nk", Jn, e)[..., None])[..., 0]
        M[a] += dp.reshape(-1, 3, 2).transpose(0, 2, 1)
        done = np.abs(r - rho[a]) < 1e-3
        rho[a] = r
        bad = ~ins | ~np.all(np.isfinite(M[a]), axis=(1, 2))
        act[a[done | bad]] = False
    S, ins = _warped_fa(stack, M, xs, ys, w, h)
    Iz = S[..., 0] - S[..., 0].mean(axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        score = np.einsum("np,np->n", Iz, Tn) / np.linalg.norm(Iz, axis=1)
    new = M[:, :, 2].astype(float) + 0.5
    shift = np.hypot(*(new - uv[live]).T)
    good = ins & (score >= min_cc) & (shift <= max_shift_px)
    cc[live] = score
    uv[live[good]] = new[good]
    lin_out[live[good]] = M[good, :, :2]
    ok[live[good]] = True
    return AffineRefinement(uv, lin_out, cc, ok)


def _warped_fa(img, M, xs, ys, w, h):
    X = M[:, 0, 0, None] * xs + M[:, 0, 1, None] * ys + M[:, 0, 2, None]
    Y = M[:, 1, 0, None] * xs + M[:, 1, 1, None] * ys + M[:, 1, 2, None]
    inside = np.all((X >= 0) & (X <= w - 1) & (Y >= 0) & (Y <= h - 1), axis=1)
    out = cv2.remap(img, X, Y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    return out.reshape(len(M), -1, img.shape[2]), inside


if __name__ == "__main__":
    import tumblenav.frontends.stereo_images.matching as matching
    import tumblenav.frontends.stereo_images.tracker as tracker

    which = sys.argv.pop(1)
    fn = {"ic": refine_ic, "fa": refine_fa}[which]
    tracker.refine_affine = matching.refine_affine = fn
    bench = Path(__file__).resolve().parents[4] / "benchmarks" / "image_frontend.py"
    sys.argv[0] = str(bench)
    runpy.run_path(str(bench), run_name="__main__")
