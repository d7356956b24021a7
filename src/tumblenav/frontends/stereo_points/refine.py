"""The template (the features' G coordinates) refined over its views on a schedule, each\nversion's rows reprocessed (beyond the paper)."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav.frontends.stereo_points.gframe import joint_features, weighted_kabsch
from tumblenav.frontends.stereo_points.settings import FrontEndSettings

Array = NDArray[np.float64]


def _refine_template(
    t, first, k_ref, upto, p_C, cov_C, p_L, cov_L, usable, known_at, template, cov_tmpl,
    R_GI, cov_G, R_CL, R_LI, refined=None,
):  # fmt: skip
    """One refinement of the template: refitted over the epochs ``first .. k_ref - 1`` of G
    (``first`` (B,), G's first epoch; ``k_ref`` (B,), the refinement's epoch, n where
    none), and G with it at the epochs ``0 .. upto - 1`` (beyond Hu 2024, whose G comes
    from three points of one sighting).

    The template (each feature's G coordinates at its first sighting: one stereo point,
    8 mm deep at 17 m and 2e-5 rad) has errors fixed in G that the G attitude fit turns
    into view-dependent attitude errors, which do not average out in the rates. At epoch
    ``k_ref`` the features are refitted jointly to all their views so far
    (``joint_features``, with a quadratic translation in L, which is the Hill motion to
    0.1 mm over 30 s), in the axes of the G attitudes ``R_GI`` measured so far (with the
    template ``template``, the previous version), so that G keeps its orientation; the
    other features' coordinates shift with the fitted ones' mean. How ``process`` uses it
    causally: G attitudes are reported with a version from its ``k_ref`` on; the rates of
    epochs from ``k_ref - h`` on (each available at its epoch + h >= k_ref) come from its
    attitudes; and the least squares, a batch re-solved at each solution, uses from
    ``k_ref`` on the rows of every epoch recomputed with it (past data reprocessed at
    ``k_ref``), before it the rows as they were.

    Tried and not kept: keeping the first G's orientation across the switch (the refined
    template rotated by the mean rotation between the two G over ``k_ref - 2h .. k_ref``):
    median attitude 0.094 -> 0.102 deg over 500 runs at 2e-5 rad, no change at 1e-6 rad.

    ``refined`` (B,): the runs whose ``template`` is a fit's already (about its fitted mass
    centre: one pass of the fit from it).

    Returns the refined template (B,N,3) (the previous one where the fit failed) and its
    covariance, G's attitude and covariance (B,upto,...) with it, ``refined`` updated, and
    the points' own noise's share of G's covariance (``weighted_kabsch``'s ``noise``)."""
    B, n, N = usable.shape
    valid = np.all(np.isfinite(R_GI), axis=(-1, -2))
    new_t = template.copy()
    new_c = cov_tmpl.copy()
    ref = np.zeros(B, dtype=bool) if refined is None else refined.copy()
    for b in np.flatnonzero(k_ref < n):
        j = np.flatnonzero(valid[b, first[b] : k_ref[b]]) + first[b]
        if len(j) < 10:
            continue
        R_LG = R_LI[b, j] @ np.swapaxes(R_GI[b, j], -1, -2)
        tau = (t[j] - t[j[0]])[:, None, None]
        eye = np.eye(3)[None]
        Phi = np.concatenate([np.broadcast_to(eye, tau.shape[:1] + (3, 3)), tau * eye,
                              0.5 * tau**2 * eye], axis=2)  # fmt: skip
        kn = known_at[b, k_ref[b] - 1]
        use = usable[b, j] & kn[None, :]
        g = template[b]
        # the lever arms: a refined template is about its fitted mass centre already (one
        # pass); the first sightings' about one feature (centred, then re-linearised)
        out = joint_features(Phi, R_LG, p_L[b, j], cov_L[b, j], cov_G[b, j], use,
                             g if ref[b] else g - np.nanmean(g[kn], axis=0),
                             passes=1 if ref[b] else 2)  # fmt: skip
        if out is None:
            continue
        _, f, cov_f, idx = out
        c = np.mean(g[idx] - f, axis=0)
        new_t[b] = g - c
        new_t[b, idx] = f
        # the template's covariance is its shape's: the features' common shift (their mass
        # centre, poorly known in a slow tumble) is a translation, which each epoch's fit
        # of G estimates anyway (with it, G got worse than unrefined at 0.024 rad/s)
        nf = len(idx)
        Pm = np.kron(np.eye(nf) - 1.0 / nf, np.eye(3))
        cov_s = Pm @ cov_f @ Pm.T
        for m, i in enumerate(idx):
            new_c[b, i] = cov_s[3 * m : 3 * m + 3, 3 * m : 3 * m + 3]
        ref[b] = True
    m = upto
    use = usable[:, :m] & known_at[:, :m] & (k_ref < n)[:, None, None]
    w = np.where(use, 1.0 / np.maximum(np.trace(cov_C[:, :m], axis1=-2, axis2=-1), 1e-30), 0.0)
    noise: dict = {}
    R2, _, c2, ok2 = weighted_kabsch(
        p_C[:, :m].reshape(B * m, N, 3),
        np.broadcast_to(new_t[:, None], (B, m, N, 3)).reshape(B * m, N, 3),
        w.reshape(B * m, N),
        cov_C[:, :m].reshape(B * m, N, 3, 3),
        np.trace(new_c, axis1=-2, axis2=-1)[..., None, None] * np.eye(3),  # as in pass 2
        run_len=m,
        noise=noise,
    )
    ok2 = ok2.reshape(B, m)
    R_GI2 = np.where(ok2[..., None, None], R2.reshape(B, m, 3, 3), np.nan) @ (
        R_CL[:, :m] @ R_LI[:, :m]
    )
    cov_G2 = np.where(ok2[..., None, None], c2.reshape(B, m, 3, 3), np.nan)
    cov_G2_noise = np.where(ok2[..., None, None], noise["cov_G"].reshape(B, m, 3, 3), np.nan)
    return new_t, new_c, R_GI2, cov_G2, ref, cov_G2_noise


def _refine_epochs(first: NDArray[np.int64], s: FrontEndSettings, dt: float, n: int):
    """The epochs (V, B) of the template's refinements (``template_refine_s`` after G's
    first epoch ``first`` (B,), each rounded up to a least-squares solution; n where it
    would be at or after the end, or G is never defined)."""
    secs = np.atleast_1d(np.asarray(s.template_refine_s, dtype=float))
    steps = sorted({int(round(x / dt)) for x in secs if x > 0})
    ks = [np.minimum(-(-(first + m) // s.ls_every) * s.ls_every, n) for m in steps]
    return [np.where(first < n, k, n) for k in ks]
