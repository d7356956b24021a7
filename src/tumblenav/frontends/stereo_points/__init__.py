"""Stereo feature points -> measurements for the Hu 2024 filter, batched over Monte Carlo runs.

From raw pixel tracks (:class:`tumblenav.measurements.StereoMeasurements`) of B runs that share a
rig and a time grid, this front end computes, for every run and epoch:

1. triangulated feature points in the rig frame C and in L, with their first-order
   covariances (Hu 2024 eq. 1 corrected; two-ray triangulation for a convergent rig);
2. the photogrammetric frame G (Hu 2024 eq. 6-7) from the best-conditioned triplet at the first
   epoch with three features, kept through occlusions by rigid alignment of any >= 3 visible
   features whose G coordinates are known (weighted Kabsch), with the covariance of its
   attitude;
3. the angular rate of G relative to I (Hu 2024 eq. 15-16) from a local linear fit of the G
   attitude over +-h epochs (the chaser's rotation removed through the known R_CI);
4. the least-squares identification of the normalised inertia and angular momentum
   (Hu 2024 eq. 9-14), accumulated over time (growing batch). Beyond the paper, each epoch is
   weighted by the inverse variance of its rate, so far-away (noisy) epochs do not spoil it;
   the template is refined on a schedule (``template_refine_s``) and each refinement
   reprocesses the batch's past rows (``_refine_template``);
5. the unique principal-axis frame (DPACF, Hu 2024 eq. 17) and the attitude measurement
   ``q_TI = q_TG (x) q_GI`` (Hu 2024 eq. 31) with a first-order covariance: eigenvector
   perturbation of the identified inertia plus the G attitude noise.

All arrays have leading shape (B, n) (runs, epochs); unavailable values are NaN.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.frontends import _points_kernel
from tumblenav.frontends.stereo_points.gframe import (  # noqa: F401
    _best_triplet_batch,
    joint_features,
    photogrammetric_frames,
    weighted_kabsch,
)
from tumblenav.frontends.stereo_points.inertia_ls import (  # noqa: F401
    _E,
    _inertia_from_l,
    _ls_rows,
    _solve_and_dpacf,
    identify_and_dpacf,
)
from tumblenav.frontends.stereo_points.rates import (  # noqa: F401
    _finite_or_identity,
    _fit_factors,
    _quats,
    _skew,
    rates_and_covariance,
    rates_noise_cov,
)
from tumblenav.frontends.stereo_points.refine import (  # noqa: F401
    _refine_epochs,
    _refine_template,
)

# every name of the submodules, as when this was one module
from tumblenav.frontends.stereo_points.settings import (  # noqa: F401
    FrontEndSettings,
    PointsFrontEnd,
    StereoPointsTuning,
)
from tumblenav.frontends.stereo_points.triangulation import (  # noqa: F401
    _finish_triangulation,
    triangulate,
)

Array = NDArray[np.float64]


def process(meas_list, settings: FrontEndSettings | None = None) -> PointsFrontEnd:
    """Run the whole front end on B runs (same rig, same time grid)."""
    s = settings or FrontEndSettings()
    t = meas_list[0].t
    dt = float(np.median(np.diff(t)))
    R_CL = rot.quat_to_matrix(np.stack([m.q_CL for m in meas_list]))  # (B,n,3,3)
    R_LI = rot.quat_to_matrix(np.stack([m.q_LI for m in meas_list]))
    R_LC = np.ascontiguousarray(np.swapaxes(R_CL, -1, -2))
    rig = meas_list[0].rig
    if rig.kind == "parallel":  # compiled: the same as triangulate() and the rotation below
        L = rig.left
        p_C, cov_C, p_L, cov_L, usable, one_cam, bad = _points_kernel.triangulate_parallel_rotated(
            np.stack([m.uv for m in meas_list]).astype(float),
            np.stack([m.observed for m in meas_list]).astype(np.bool_),
            float(L.focal_px),
            float(rig.baseline_m),
            float(L.principal_point_px[0]),
            float(L.principal_point_px[1]),
            float(meas_list[0].noise_px),
            R_LC,
        )
        skipped = {"one_camera_only": one_cam, "bad_triangulation": bad}
    else:
        p_C, cov_C, usable, skipped = triangulate(meas_list)
        p_L = (R_LC[:, :, None] @ p_C[..., None])[..., 0]
        cov_L = R_LC[:, :, None] @ cov_C @ np.swapaxes(R_LC, -1, -2)[:, :, None]
    h = s.rate_half_window
    n = len(t)
    full = s.g_fit == "full"
    steps: Array | list[float] = (
        np.atleast_1d(np.asarray(s.template_refine_s, dtype=float)) if full else []
    )
    n_first = int(round(min([x for x in steps if x > 0], default=0.0) / dt))
    info: dict = {}
    R_GC, cov_G, template, known, known_at = photogrammetric_frames(
        p_C, cov_C, usable, full_cov=full, stop_after=n_first, info=info,
        stop_every=s.ls_every,
    )  # fmt: skip
    # Versions of the template (the first sightings', then each refinement's) and of what
    # follows from it: G at the epochs it is needed for (up to the next refinement), the
    # rates and the least squares' rows; each version is reported from its refinement on
    ks = _refine_epochs(info["first"], s, dt, n) if n_first > 0 else []
    ks = [k for k in ks if np.any(k < n)]
    bounds = [np.zeros(len(meas_list), dtype=np.int64)] + ks + [np.full(len(meas_list), n)]
    R_GI = R_GC @ R_CL @ R_LI
    history = [(bounds[0], template)]
    vers = []  # (R_GI, cov_G, omega, cov_fit, cov_w) over the version's first epochs
    vers_noise = []  # the rates' fit noise from the points' own noise alone (rates_noise_cov)
    cov_Gn = info["cov_G_noise"]
    tmpl, cov_t = template, info.get("cov_template")
    fitted = np.zeros(len(meas_list), dtype=bool)  # runs whose template is a fit's
    for v in range(len(bounds) - 1):
        m = min(int(bounds[v + 1].max()), n)  # a rate before bounds[v+1] - h needs no more
        if v > 0:  # refine at bounds[v], with the previous version's G
            tmpl, cov_t, R_GI, cov_G, fitted, cov_Gn = _refine_template(
                t, info["first"], bounds[v], m, p_C, cov_C, p_L, cov_L, usable, known_at,
                tmpl, cov_t, R_GI, cov_G, R_CL, R_LI, refined=fitted,
            )  # fmt: skip
            history.append((bounds[v], tmpl))
        Rv, cGv = R_GI[:, :m], cov_G[:, :m]
        # the runs' last version (the rows the least squares accumulates to the end), and
        # with unbiased_early every version: the unbiased rate fit (see rates_and_covariance)
        last = (bounds[v + 1] >= n) & (v > 0) & s.unbiased_last
        last = last | (s.unbiased_early & s.unbiased_last)
        fit: dict = {}
        vers.append(
            (Rv, cGv) + rates_and_covariance(Rv, cGv, dt, h, unbiased=last, details=fit) + (fit,)
        )
        vers_noise.append(rates_noise_cov(cov_Gn[:, :m], fit["cubic"], dt, h))
    # as reported at each epoch: G from a version's refinement on, the rate of epoch j (known
    # at j + h) from the version in force at j + h
    R_GI = np.full((len(meas_list), n, 3, 3), np.nan)
    cov_G, omega_G, cov_w = R_GI.copy(), R_GI[..., 0].copy(), R_GI.copy()
    ep = np.arange(n)[None, :]
    for v, (Rv, cGv, omv, _, cwv, _) in enumerate(vers):
        m = Rv.shape[1]
        sel = (ep >= bounds[v][:, None]) & (ep < bounds[v + 1][:, None])
        R_GI[:, :m] = np.where(sel[:, :m, None, None], Rv, R_GI[:, :m])
        cov_G[:, :m] = np.where(sel[:, :m, None, None], cGv, cov_G[:, :m])
        sel = (ep + h >= bounds[v][:, None]) & (ep + h < bounds[v + 1][:, None])
        omega_G[:, :m] = np.where(sel[:, :m, None], omv, omega_G[:, :m])
        cov_w[:, :m] = np.where(sel[:, :m, None, None], cwv, cov_w[:, :m])
    skipped["too_few_features"] = np.sum(~np.all(np.isfinite(R_GI), axis=(-1, -2)), axis=1)
    var_w = np.trace(cov_w, axis1=-2, axis2=-1) / 3.0
    # the least squares: the last version's rows, those of the earlier versions for the
    # solutions before the next refinement
    R_ls, cG_ls, om_ls, cf_ls, cw_ls, fit_ls = vers[-1]
    before = [
        (om, np.trace(cw, axis1=-2, axis2=-1) / 3.0, Rv, cf if full else None, bounds[v],
         bounds[v + 1], fd, cGv, vers_noise[v])
        for v, (Rv, cGv, om, cf, cw, fd) in enumerate(vers[:-1])
    ]  # fmt: skip
    R_GT, moments, q_TI, cov_TI, cov_frame, cov_ratios, frame_gate = identify_and_dpacf(
        om_ls,
        np.trace(cw_ls, axis1=-2, axis2=-1) / 3.0,
        R_ls,
        cov_G,
        s,
        delay=s.rate_half_window,
        cov_w=cf_ls if full else None,
        R_GI_report=R_GI,
        before=before,
        fit=fit_ls,
        dt=dt,
        cov_G_rows=cG_ls,
        cov_w_noise=vers_noise[-1],
    )
    return PointsFrontEnd(
        t=t,
        p_L=p_L,
        cov_L=cov_L,
        usable=usable,
        R_GI=R_GI,
        cov_G=cov_G,
        omega_G=omega_G,
        var_omega=var_w,
        template_G=tmpl,
        known=known,
        known_at=known_at,
        R_GT=R_GT,
        moments=moments,
        q_TI=q_TI,
        cov_TI=cov_TI,
        cov_frame=cov_frame,
        cov_ratios=cov_ratios,
        frame_gate=frame_gate,
        skipped=skipped,
        cov_omega=cov_w,
        template_history=history if len(history) > 1 else None,
    )
