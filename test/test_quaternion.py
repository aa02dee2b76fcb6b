"""Quaternion algebra of Section 2: identities, round trips, stability at 180 degrees."""

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat

# Rounding of a few float64 operations on unit-size numbers.
TIGHT = 1e-12


def random_unit_quaternions(rng, n):
    return quat.normalize(rng.normal(size=(n, 4)))


quaternions = st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(
    lambda v: np.linalg.norm(v) > 0.1).map(lambda v: quat.normalize(np.array(v)))


def same_rotation(p, q):
    """Measure how far p is from being the same rotation as q (q or -q)."""
    return min(np.max(np.abs(p - q)), np.max(np.abs(p + q)))


def test_plus_and_minus_matrices_are_the_products_of_eq_13():
    rng = np.random.default_rng(1)
    for a, b in zip(rng.normal(size=(20, 4)), rng.normal(size=(20, 4))):
        product = quat.multiply(a, b)
        assert_allclose(quat.plus_matrix(a) @ b, product, atol=TIGHT)
        assert_allclose(quat.minus_matrix(b) @ a, product, atol=TIGHT)
        # eq. (18): P-(p) = P+(p)^T for the conjugate, i.e. minus(p) == plus(p*)^T ... and
        # the rotation of eq. (18) is plus(p) minus(p*).
        assert_allclose(quat.minus_matrix(quat.conjugate(b)), quat.minus_matrix(b).T,
                        atol=TIGHT)


def test_hamilton_product_units():
    i, j, k = np.eye(4)[1], np.eye(4)[2], np.eye(4)[3]
    assert_allclose(quat.multiply(i, j), k)
    assert_allclose(quat.multiply(j, k), i)
    assert_allclose(quat.multiply(k, i), j)
    assert_allclose(quat.multiply(i, i), -np.eye(4)[0])


@settings(max_examples=200, deadline=None)
@given(quaternions, quaternions)
def test_matrix_of_product_is_product_of_matrices(p, q):
    assert_allclose(quat.matrix_from_quaternion(quat.multiply(p, q)),
                    quat.matrix_from_quaternion(p) @ quat.matrix_from_quaternion(q),
                    atol=TIGHT)


@settings(max_examples=300, deadline=None)
@given(quaternions)
def test_round_trip_quaternion_matrix_quaternion(p):
    back = quat.quaternion_from_matrix(quat.matrix_from_quaternion(p))
    assert same_rotation(back, p) < TIGHT
    assert back[0] >= -1e-15   # w within rounding of 0 is a half turn: sign by x, y, z


@settings(max_examples=200, deadline=None)
@given(quaternions, st.lists(st.floats(-1, 1), min_size=3, max_size=3))
def test_rotation_of_eq_19_equals_matrix_of_eq_20(p, v):
    rotated = quat.multiply(quat.multiply(p, np.concatenate([[0.0], v])), quat.conjugate(p))
    assert_allclose(rotated[1:], quat.matrix_from_quaternion(p) @ v, atol=TIGHT)


@pytest.mark.parametrize('angle_deg', [0.0, 1e-9, 90.0, 179.9, 179.999999, 180.0])
def test_matrix_to_quaternion_is_stable_up_to_180_degrees(angle_deg):
    rng = np.random.default_rng(7)
    for axis in rng.normal(size=(50, 3)):
        p = quat.from_axis_angle(axis, np.radians(angle_deg))
        back = quat.quaternion_from_matrix(quat.matrix_from_quaternion(p))
        assert same_rotation(back, p) < TIGHT
        assert_allclose(quat.rotation_angle(back), np.radians(angle_deg), atol=1e-12)


def test_matrix_formula_eq_20_equals_euler_formula_eq_21():
    rng = np.random.default_rng(3)
    for axis, angle in zip(rng.normal(size=(20, 3)), rng.uniform(0, 2 * np.pi, 20)):
        u = axis / np.linalg.norm(axis)
        euler = (np.cos(angle) * np.eye(3) + (1 - np.cos(angle)) * np.outer(u, u)
                 + np.sin(angle) * quat.skew(u))
        assert_allclose(quat.matrix_from_quaternion(quat.from_axis_angle(u, angle)), euler,
                        atol=TIGHT)


def test_batched_matrix_matches_single():
    rng = np.random.default_rng(4)
    q = random_unit_quaternions(rng, 10)
    batch = quat.matrix_from_quaternion(q)
    for k in range(10):
        assert_allclose(batch[k], quat.matrix_from_quaternion(q[k]), atol=TIGHT)


def test_axis_angle_and_rotation_vector_round_trip():
    rng = np.random.default_rng(5)
    for p in random_unit_quaternions(rng, 50):
        axis, angle = quat.axis_angle(p)
        assert same_rotation(quat.from_axis_angle(axis, angle), p) < TIGHT
        assert same_rotation(quat.from_rotation_vector(quat.rotation_vector(p)), p) < TIGHT
    assert_allclose(quat.from_rotation_vector(np.zeros(3)), quat.IDENTITY)


def test_angle_between_resolves_tiny_angles():
    p = quat.from_axis_angle([1, 2, 3], 1.0)
    q = quat.multiply(p, quat.from_axis_angle([0, 0, 1], 1e-12))
    assert_allclose(quat.angle_between(p, q), 1e-12, rtol=1e-3)
    assert_allclose(quat.angle_between(p, -q), 1e-12, rtol=1e-3)


def test_canonical_is_unique_per_rotation():
    p = np.array([0.0, -0.6, 0.8, 0.0])
    assert_allclose(quat.canonical(p), -p)
    assert_allclose(quat.canonical(-p), -p)
    assert quat.canonical(np.array([-0.5, 0.5, 0.5, 0.5]))[0] > 0
    # Many at once, the same rule: w decides, else the first non-zero component.
    batch = np.array([p, -p, [-0.5, 0.5, 0.5, 0.5], [0.0, 0.0, 0.0, -1.0], [0.6, 0.0, -0.8, 0.0]])
    assert_allclose(quat.canonical(batch), [quat.canonical(row) for row in batch])
    assert_allclose(quat.canonical(batch[[2, 4]]), [quat.canonical(row) for row in batch[[2, 4]]])


def test_ros_order_converters_are_inverse_and_named_by_direction():
    wxyz = np.array([0.1, 0.2, 0.3, 0.4])
    assert_allclose(quat.xyzw_from_wxyz(wxyz), [0.2, 0.3, 0.4, 0.1])
    assert_allclose(quat.wxyz_from_xyzw(quat.xyzw_from_wxyz(wxyz)), wxyz)


def test_slerp_is_exact_for_constant_angular_velocity():
    p = quat.from_axis_angle([0, 1, 0], 0.2)
    step = quat.from_axis_angle([1, 1, 0], 1.0)
    q = quat.multiply(step, p)
    middle = quat.slerp(p, q, 0.25)
    expected = quat.multiply(quat.from_axis_angle([1, 1, 0], 0.25), p)
    assert same_rotation(middle, expected) < TIGHT


def test_average_ignores_signs_and_finds_the_mean():
    rng = np.random.default_rng(6)
    center = quat.from_axis_angle([1, 0, 0], 0.5)
    noisy = [quat.multiply(center, quat.from_rotation_vector(rng.normal(size=3) * 0.01))
             for _ in range(200)]
    noisy = [q if k % 2 else -q for k, q in enumerate(noisy)]
    # 200 samples of 0.01 rad per-axis noise: the mean is within ~0.01 * 3 / sqrt(200).
    assert quat.angle_between(quat.average(noisy), center) < 0.003


def test_normalize_refuses_zero():
    with pytest.raises(ValueError, match='zero quaternion'):
        quat.normalize(np.zeros(4))


def test_slerp_broadcasts_and_matches_row_by_row():
    rng = np.random.default_rng(8)
    p, q = random_unit_quaternions(rng, 50), random_unit_quaternions(rng, 50)
    q[:5] = p[:5] * (1.0 - 1e-12)          # (nearly) equal rows take the linear branch
    f = rng.uniform(0.0, 1.0, 50)
    many = quat.slerp(p, q, f)
    for k in range(50):
        assert same_rotation(many[k], quat.slerp(p[k], q[k], f[k])) < TIGHT


def test_slerp_is_exact_for_small_steps_too():
    p = quat.from_axis_angle([0, 1, 0], 0.2)
    for step in (1e-6, 1e-3, 0.05):
        q = quat.multiply(quat.from_axis_angle([1, 2, 3], step), p)
        expected = quat.multiply(quat.from_axis_angle([1, 2, 3], 0.3 * step), p)
        assert same_rotation(quat.slerp(p, q, 0.3), expected) < TIGHT


def test_rotate_matches_the_matrix():
    rng = np.random.default_rng(9)
    q, v = random_unit_quaternions(rng, 20), rng.normal(size=(20, 3))
    assert_allclose(quat.rotate(q, v),
                    np.einsum('kij,kj->ki', quat.matrix_from_quaternion(q), v), atol=TIGHT)
