"""Davenport's q-method (Chang 2021 eq. 27-28) in tumblenav's Hamilton convention, against
scipy's Rotation.align_vectors (the oracle, notes Sec. 3.3), and its first-order covariance."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from tumblenav import rotations as rot
from tumblenav.estimators.chang2021.qmethod import (
    davenport_matrix,
    q_method,
    q_method_covariance,
)


def _angle(q1, q2):
    return float(rot.quat_angle(rot.quat_multiply(q1, rot.quat_conjugate(q2))))


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    m=st.integers(3, 60),
    noise=st.sampled_from([0.0, 1e-3, 0.05]),
    spread=st.sampled_from([1.0, 1e-2]),  # 1e-2: nearly collinear sets
)
def test_q_method_equals_align_vectors(seed, m, noise, spread):
    rng = np.random.default_rng(seed)
    R = Rotation.random(random_state=seed)
    b = rng.normal(size=(m, 3)) * np.array([1.0, spread, spread])
    a = R.apply(b) + noise * rng.normal(size=(m, 3))
    w = rng.uniform(0.2, 3.0, m)
    q, lam = q_method(a, b, w)
    R_ref, _ = Rotation.align_vectors(a, b, w)
    # both minimise the same weighted loss: compare the losses (robust when the rotation is
    # nearly undetermined), and the rotations where it is well determined
    loss = lambda Rm: float(np.sum(w * np.sum((a - b @ Rm.T) ** 2, axis=1)))  # noqa: E731
    l_q, l_ref = loss(rot.quat_to_matrix(q)), loss(R_ref.as_matrix())
    assert l_q <= l_ref + 1e-9 * (1 + l_ref)
    if lam[3] - lam[2] > 1e-3 * lam[3]:  # a well-determined rotation: the same one
        assert _angle(q, R_ref.as_quat()) < 1e-6
    assert abs(np.linalg.norm(q) - 1) < 1e-12 and q[3] >= 0


def test_noiseless_lambda_max_is_sum_of_weights_and_jpl_is_the_transpose():
    rng = np.random.default_rng(1)
    R = Rotation.random(random_state=2)
    b = rng.normal(size=(20, 3))
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    a = R.apply(b)
    w = rng.uniform(0.5, 2.0, 20)
    q, lam = q_method(a, b, w)
    assert np.isclose(lam[3], w.sum(), rtol=1e-12)
    assert _angle(q, R.as_quat()) < 1e-7
    # Chang's eq. 27 as printed (Shuster z) gives the transpose (notes Sec. 0.7)
    K = davenport_matrix(a, b, w)
    K[:3, 3] *= -1
    K[3, :3] *= -1
    _, V = np.linalg.eigh(K)
    assert np.allclose(rot.quat_to_matrix(V[:, 3]), R.as_matrix().T, atol=1e-7)


def test_perturbing_the_optimum_raises_the_loss():
    rng = np.random.default_rng(3)
    b = rng.normal(size=(30, 3))
    a = Rotation.random(random_state=4).apply(b) + 0.01 * rng.normal(size=(30, 3))
    q, _ = q_method(a, b)
    loss = lambda qq: np.sum((a - b @ rot.quat_to_matrix(qq).T) ** 2)  # noqa: E731
    for d in rng.normal(size=(10, 3)) * 1e-3:
        assert loss(rot.boxplus(q, d)) > loss(q)


def test_covariance_matches_monte_carlo():
    rng = np.random.default_rng(5)
    R = Rotation.random(random_state=6)
    b = rng.normal(size=(40, 3))
    sig = 0.01
    errs = []
    for _ in range(1500):
        a = R.apply(b) + sig * rng.normal(size=(40, 3))
        errs.append(rot.boxminus(q_method(a, b)[0], R.as_quat()))
    C = np.cov(np.array(errs).T)
    P, _ = q_method_covariance(R.as_quat(), b, np.ones(40), np.tile(sig**2 * np.eye(3), (40, 1, 1)))
    # 1500 samples: each variance within ~10 % (4 sigma of its sampling error is 15 %)
    assert np.allclose(np.diag(C), np.diag(P), rtol=0.15)
