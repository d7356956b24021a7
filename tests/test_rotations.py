"""Quaternion conventions cross-checked against scipy (the oracle; same [x,y,z,w] order)."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from tumblenav import rotations as rot

finite = st.floats(-1.0, 1.0, allow_nan=False)
quat4 = arrays(np.float64, 4, elements=finite).filter(lambda q: np.linalg.norm(q) > 0.1)
vec3 = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False))
small3 = arrays(np.float64, 3, elements=st.floats(-1e-3, 1e-3, allow_nan=False))


def _unit(q):
    return q / np.linalg.norm(q)


@given(quat4, quat4)
def test_hamilton_product_matches_scipy_composition(p, q):
    p, q = _unit(p), _unit(q)
    ours = rot.quat_multiply(p, q)
    ref = (Rotation.from_quat(p) * Rotation.from_quat(q)).as_quat()
    assert np.allclose(rot.quat_normalize(ours), rot.quat_normalize(ref), atol=1e-12)
    # R(p (x) q) = R(p) R(q): q_AC = q_AB (x) q_BC
    assert np.allclose(
        rot.quat_to_matrix(ours), rot.quat_to_matrix(p) @ rot.quat_to_matrix(q), atol=1e-12
    )


@given(quat4, vec3)
def test_matrix_and_rotate_match_scipy(q, v):
    q = _unit(q)
    R = Rotation.from_quat(q)
    assert np.allclose(rot.quat_to_matrix(q), R.as_matrix(), atol=1e-12)
    assert np.allclose(rot.quat_rotate(q, v), R.apply(v), atol=1e-12)
    back = rot.matrix_to_quat(R.as_matrix())
    assert back[3] >= 0.0
    # q and -q are the same rotation: compare up to that sign
    assert min(np.abs(back - q).max(), np.abs(back + q).max()) < 1e-9


@given(arrays(np.float64, 3, elements=st.floats(-3.0, 3.0, allow_nan=False)))
def test_exp_log_round_trip_and_scipy(phi):
    q = rot.exp_quat(phi)
    assert np.isclose(np.linalg.norm(q), 1.0)
    assert np.allclose(
        rot.quat_normalize(q), rot.quat_normalize(Rotation.from_rotvec(phi).as_quat())
    )
    assert np.allclose(rot.exp_map(phi), Rotation.from_rotvec(phi).as_matrix(), atol=1e-12)
    # the log returns the angle in [0, pi]; compare as rotations
    back = rot.log_quat(q)
    assert np.linalg.norm(back) <= np.pi + 1e-12
    assert np.allclose(rot.exp_map(back), rot.exp_map(phi), atol=1e-9)


@given(small3)
def test_small_angle_error_state(dtheta):
    q_hat = rot.exp_quat(np.array([0.3, -1.1, 0.7]))
    q = rot.boxplus(q_hat, dtheta)
    assert np.allclose(rot.boxminus(q, q_hat), dtheta, atol=1e-12)
    # Exp(dtheta) ~ I + [dtheta x] to first order (Hamilton sign)
    R_err = rot.quat_to_matrix(q) @ rot.quat_to_matrix(q_hat).T
    assert np.allclose(R_err, np.eye(3) + rot.skew(dtheta), atol=1e-6)
    assert np.isclose(
        rot.quat_angle(rot.quat_multiply(q, rot.quat_conjugate(q_hat))),
        np.linalg.norm(dtheta),
        atol=1e-12,
    )


@given(quat4, vec3)
def test_kinematics_sign(q, w):
    """dR_TI/dt = -[w x] R_TI for dq_TI/dt = -1/2 [w;0] (x) q_TI."""
    q = _unit(q)
    dq = rot.quat_derivative(q, w)
    h = 1e-6
    dR = (rot.quat_to_matrix(q + h * dq) - rot.quat_to_matrix(q - h * dq)) / (2 * h)
    assert np.allclose(dR, -rot.skew(w) @ rot.quat_to_matrix(q), atol=1e-6)


def test_scalar_first_conversion():
    q_wxyz = np.array([0.9707, 0.1386, 0.1386, 0.1386])  # Kabir 2025 Sec. 3.2 initial guess
    q = rot.from_scalar_first(q_wxyz)
    assert np.allclose(q, [0.1386, 0.1386, 0.1386, 0.9707])
    assert np.allclose(rot.to_scalar_first(q), q_wxyz)


def test_stacks_broadcast():
    rng = np.random.default_rng(1)
    q = rot.quat_normalize(rng.normal(size=(5, 7, 4)))
    assert rot.quat_to_matrix(q).shape == (5, 7, 3, 3)
    assert rot.quat_multiply(q, q[0]).shape == (5, 7, 4)
    assert rot.matrix_to_quat(rot.quat_to_matrix(q)).shape == (5, 7, 4)


# --- the fast twins (matrix-product forms for large stacks) equal the references ----------
stack4 = arrays(np.float64, (5, 4), elements=finite).filter(
    lambda q: np.all(np.linalg.norm(q, axis=-1) > 0.1)
)
stack3 = arrays(np.float64, (5, 3), elements=st.floats(-3.0, 3.0, allow_nan=False))


@given(stack4, stack4, stack3)
def test_fast_twins_equal_the_references(p, q, w):
    # stacks and broadcasting as the unscented filters use them
    np.testing.assert_allclose(rot.quat_multiply_fast(p, q), rot.quat_multiply(p, q), atol=1e-15)
    np.testing.assert_allclose(
        rot.quat_multiply_fast(p[:, None], q[None]), rot.quat_multiply(p[:, None], q[None]),
        atol=1e-15,
    )  # fmt: skip
    np.testing.assert_allclose(
        rot.quat_derivative_fast(q, w), rot.quat_derivative(q, w), atol=1e-14
    )
    # not necessarily unit: both normalise
    np.testing.assert_allclose(rot.quat_to_matrix_fast(3.0 * q), rot.quat_to_matrix(q), atol=1e-14)
    pu, qu = p / np.linalg.norm(p, axis=-1, keepdims=True), q / np.linalg.norm(q, axis=-1)[:, None]
    np.testing.assert_allclose(rot.boxplus_fast(qu, 0.3 * w), rot.boxplus(qu, 0.3 * w), atol=1e-15)
    np.testing.assert_allclose(rot.boxminus_fast(pu, qu), rot.boxminus(pu, qu), atol=1e-12)
