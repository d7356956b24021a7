"""Kabir 2025 UKF start: given (e.g. the recipe's truth-based guess) or triangulated from the
first measurements alone."""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from tumblenav import rotations as rot
from tumblenav.errors import InputError
from tumblenav.estimators.kabir2025.model import KabirGeometry
from tumblenav.estimators.kabir2025.tuning import KabirTuning
from tumblenav.frontends import projections as proj

Array = NDArray[np.float64]
Variant = Literal["additive", "mult"]


def initial_state(
    scenario: Any, t: Array, z: Array, geom: KabirGeometry, tun: KabirTuning, variant: Variant
) -> tuple[Array, Array]:
    """``x0`` (nominal) and ``P0`` (24x24 for ``additive``, 23x23 for ``mult``) at ``t[0]``.

    ``init: triangulated`` uses the measurements ``z`` (n, N, 9) of the first epochs only;
    ``init: given`` the settings' ``init_omega_rad_s``, ``init_q_TI``, ``init_features_m``
    (``k = 0``), e.g. Kabir 2025 Sec. 3.2's truth-based guess made by the kabir2025 recipe.
    """
    N = z.shape[1]
    x = np.zeros(9 + 3 * N)
    if tun.init == "given":
        x[0:3] = tun.init_omega_rad_s
        q = np.asarray(tun.init_q_TI, dtype=float)
        if not np.linalg.norm(q) > 0:
            raise InputError("estimator.tuning.init_q_TI: must be a nonzero quaternion")
        x[3:7] = rot.quat_normalize(q)
        p = np.asarray(tun.init_features_m, dtype=float).reshape(-1, 3)
        if p.shape[0] != N:
            raise InputError(
                f"estimator.tuning.init_features_m: {p.shape[0]} features given, the "
                f"measurements have {N}"
            )
        x[9:] = p.ravel()
    else:
        x[0:3], x[3:7], x[9:] = _triangulated_start(t, z, geom)
    if variant == "additive":
        var = [tun.p0_omega_var] * 3 + [tun.p0_quat_var] * 4
    else:  # dtheta = 2 dq_vec
        var = [tun.p0_omega_var] * 3 + [4.0 * tun.p0_quat_var] * 3
    var += [tun.p0_k_var] * 2 + [tun.p0_feature_var] * (3 * N)
    return x, np.diag(var)


def _triangulated_start(t: Array, z: Array, geom: KabirGeometry) -> tuple[Array, Array, Array]:
    """At ``t[0]``: q_TI = identity (T := I); features triangulated in C; omega_C by least
    squares on ``w_dot = A omega`` (Kabir 2025 eq. 18-19) with the flow from the one-sided
    second-order difference of the first three epochs' projections (else ``z[0]``'s flow)."""
    z0 = z[0]
    cl, cr = geom.centres_x
    ok = np.all(np.isfinite(z0[:, [0, 1, 2, 4]]), axis=1)
    if ok.sum() < 2:
        raise InputError("estimator.tuning.init: 'triangulated' needs >= 2 stereo features at t0")
    y = (cr - cl) / z0[:, 4]  # disparity u_L - u_R = b / y
    rho = np.stack([z0[:, 2] * y + cl, y, z0[:, 1] * y], -1)
    rho0 = geom.rho0_C[0]
    flow = z0[:, 5:9]
    if len(t) >= 3 and np.isclose(t[2] - t[1], t[1] - t[0]):
        w = z[:3, :, 0:4]
        one_sided = (-3.0 * w[0] + 4.0 * w[1] - w[2]) / (2.0 * (t[1] - t[0]))
        flow = np.where(np.isfinite(one_sided), one_sided, flow)
    A_R, A_L = proj.flow_matrices(rho, rho0, geom.centres_x)
    A = np.concatenate([A_R, A_L], axis=1).reshape(-1, 3)  # rows du_R, dv_R, du_L, dv_L
    J = proj.projection_jacobian(rho, geom.centres_x)[:, ::-1].reshape(len(z0), 4, 3)
    b = (flow - J @ geom.rho0_dot_C[0]).reshape(-1)  # flow of the rotation alone
    use = np.repeat(ok, 4) & np.isfinite(b)
    if use.sum() < 6:
        raise InputError("estimator.tuning.init: 'triangulated' needs the flow of >= 2 features")
    omega_C = np.linalg.lstsq(A[use], b[use], rcond=None)[0]
    R_TC = geom.R_CI.T  # q_TI = identity: T = I
    p = np.where(ok[:, None], (rho - rho0) @ R_TC.T, 0.0)
    return R_TC @ omega_C, rot.IDENTITY.copy(), p.ravel()
