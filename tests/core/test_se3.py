"""SE(3) algebra: exp/log round trips, small-angle behaviour, adjoint identity."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from tasks.core import se3

finite = st.floats(-1e3, 1e3, allow_nan=False)
angles = st.floats(-3.1, 3.1, allow_nan=False)


def twist(v, w):
    return np.concatenate([v, w])


@settings(max_examples=200, deadline=None)
@given(arrays(float, 3, elements=finite), arrays(float, 3, elements=st.floats(-1.8, 1.8)))
def test_log_inverts_exp_for_rotations_below_pi(v, w):
    xi = twist(v, w)
    assert np.allclose(se3.log(se3.exp(xi)), xi, atol=1e-8 * (1 + np.abs(xi).max()))


@settings(max_examples=200, deadline=None)
@given(arrays(float, 6, elements=finite))
def test_exp_of_log_is_identity_on_the_group(x):
    T = se3.exp(np.concatenate([x[:3], x[3:] % 3.0]))
    assert np.allclose(se3.exp(se3.log(T)), T, atol=1e-9 * (1 + np.abs(T).max()))


@settings(max_examples=100, deadline=None)
@given(arrays(float, 6, elements=st.floats(-1e-5, 1e-5)))
def test_small_twists_follow_first_order_and_round_trip(xi):
    T = se3.exp(xi)
    # first order: exp(xi) = I + hat(xi) + O(|xi|^2)
    assert np.allclose(T, np.eye(4) + se3.hat(xi), atol=1e-9)
    assert np.allclose(se3.log(T), xi, atol=1e-15)


def test_series_and_closed_form_agree_across_the_switch():
    w_dir = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for theta in (0.99e-4, 1.01e-4):
        xi = np.concatenate([[1.0, 2.0, 3.0], theta * w_dir])
        T = se3.exp(xi)
        # compare with scipy's matrix exponential of the se(3) matrix
        from scipy.linalg import expm

        assert np.allclose(T, expm(se3.hat(xi)), atol=1e-14)
        assert np.allclose(se3.log(T), xi, atol=1e-13)


def test_log_near_pi():
    for theta in (np.pi - 1e-7, np.pi - 1e-4, np.pi):
        w = theta * np.array([0.0, 0.6, 0.8])
        R = se3.exp_so3(w)
        w2 = se3.log_so3(R)
        assert np.allclose(se3.exp_so3(w2), R, atol=1e-9)
        assert abs(np.linalg.norm(w2) - theta) < 1e-7


@settings(max_examples=100, deadline=None)
@given(arrays(float, 6, elements=finite), arrays(float, 6, elements=st.floats(-2, 2)))
def test_adjoint_maps_twists_like_conjugation(x, xi):
    T = se3.exp(np.concatenate([x[:3], x[3:] % 2.0]))
    lhs = se3.hat(se3.adjoint(T) @ xi)
    rhs = T @ se3.hat(xi) @ se3.inverse(T)
    assert np.allclose(lhs, rhs, atol=1e-9 * (1 + np.abs(rhs).max()))


def test_batched_matches_single():
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(5, 7, 6))
    T = se3.exp(xi)
    for i in range(5):
        for j in range(7):
            assert np.allclose(T[i, j], se3.exp(xi[i, j]))
    assert np.allclose(se3.inverse(T) @ T, np.eye(4), atol=1e-12)


def test_error_motion_is_the_product_of_eq_8():
    e = np.array([0.01, -0.02, 0.03, 1e-4, -2e-4, 3e-4])
    unit = np.eye(6)
    product = np.eye(4)
    for k in range(6):
        product = product @ se3.exp(unit[k] * e[k])
    assert np.allclose(se3.error_motion(e), product, atol=1e-15)
