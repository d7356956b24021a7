"""The compiled quaternion kernels (tumblenav.rotations_compiled) against their numpy
references (tumblenav.rotations), one test each, on hypothesis-drawn inputs (seeded by the
conftest profile).  Called from Python they run without fastmath, so they agree to rounding."""

import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays
from scipy.spatial.transform import Rotation

from tumblenav import rotations as rot
from tumblenav import rotations_compiled as rc

quat = arrays(np.float64, 4, elements=st.floats(-1.0, 1.0)).filter(
    lambda q: np.linalg.norm(q) > 0.1
)
unit = quat.map(lambda q: q / np.linalg.norm(q))
rotvec = arrays(np.float64, 3, elements=st.floats(-3.0, 3.0))
tiny = arrays(np.float64, 3, elements=st.floats(-1e-9, 1e-9))


@given(quat, quat)
def test_quat_multiply(a, b):
    out = np.empty(4)
    rc.quat_multiply(a, b, out)
    np.testing.assert_allclose(out, rot.quat_multiply(a, b), rtol=0, atol=1e-15)
    rc.quat_multiply(a, b, a)  # in place
    np.testing.assert_array_equal(a, out)


@given(quat)
def test_quat_to_matrix(q):
    R = np.empty((3, 3))
    rc.quat_to_matrix(q, R)  # normalises, as the reference
    np.testing.assert_allclose(R, rot.quat_to_matrix(q), rtol=0, atol=1e-15)


@given(st.one_of(rotvec, tiny))
def test_exp_quat(phi):
    out = np.empty(4)
    rc.exp_quat(phi, out)
    np.testing.assert_allclose(out, rot.exp_quat(phi), rtol=0, atol=1e-15)


@given(quat)
def test_log_quat(q):
    out = np.empty(3)
    rc.log_quat(q, out)  # normalises, scalar part made non-negative, as the reference
    np.testing.assert_allclose(out, rot.log_quat(q), rtol=0, atol=1e-14)


@given(unit, st.one_of(rotvec, tiny))
def test_boxplus(q_hat, dtheta):
    out = np.empty(4)
    rc.boxplus(q_hat, dtheta, out)
    np.testing.assert_allclose(out, rot.boxplus(q_hat, dtheta), rtol=0, atol=1e-15)


@given(unit, unit)
def test_boxminus(q, q_hat):
    out = np.empty(3)
    rc.boxminus(q, q_hat, out)
    np.testing.assert_allclose(out, rot.boxminus(q, q_hat), rtol=0, atol=1e-13)


@given(arrays(np.float64, (6, 4), elements=st.floats(-1.0, 1.0)))
def test_matrix_to_quat(qs):
    qs = qs[np.linalg.norm(qs, axis=-1) > 0.1]
    qs = qs / np.linalg.norm(qs, axis=-1, keepdims=True)
    # exact rotations, including half turns (trace -1) and the identity (every branch)
    R = np.concatenate(
        [
            Rotation.from_quat(qs).as_matrix().reshape(-1, 3, 3),
            np.diag([1.0, -1.0, -1.0])[None],
            np.diag([-1.0, 1.0, -1.0])[None],
            np.diag([-1.0, -1.0, 1.0])[None],
            np.eye(3)[None],
        ]
    )
    np.testing.assert_allclose(rc.matrix_to_quat(R), rot.matrix_to_quat(R), rtol=0, atol=1e-14)
