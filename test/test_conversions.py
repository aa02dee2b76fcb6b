"""Tests of quatcal_ros.ros.conversions with rclpy's geometry_msgs and with rosbags' classes."""

import subprocess
import sys
from types import SimpleNamespace

from geometry_msgs.msg import Point, PoseStamped, PoseWithCovarianceStamped, Quaternion
from geometry_msgs.msg import Transform, Vector3
import numpy as np
from numpy.testing import assert_allclose, assert_array_equal
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import covariance_problem, Pose
from quatcal_ros.ros import conversions as conv
from quatcal_ros.sim import simulation as sim
from rclpy.serialization import deserialize_message, serialize_message

STAMPS = [0, 1, 999_999_999, 1_000_000_000, sim.DEFAULT_START_NS + 123_456_789,
          -1, -1_500_000_000, (2 ** 31 - 1) * 10 ** 9 + 999_999_999]


@pytest.fixture(scope='module')
def typestore():
    """Return the rosbags typestore of ROS 2 Jazzy (skip where rosbags is not installed)."""
    typesys = pytest.importorskip('rosbags.typesys')
    return typesys.get_typestore(typesys.Stores.ROS2_JAZZY)


def _random_poses(n, seed=0):
    rng = np.random.default_rng(seed)
    return [Pose(rng.normal(size=3), q) for q in sim.random_quaternions(rng, n)]


def _assert_same_pose(a, b):
    assert_allclose(a.position, b.position, rtol=0, atol=0)      # doubles travel exactly
    assert_allclose(a.quaternion, b.quaternion, rtol=0, atol=1e-15)


def test_fields_are_mapped_by_name_not_position():
    pose = Pose(np.array([1.0, 2.0, 3.0]), quat.normalize([0.1, 0.2, 0.3, 0.9]))
    msg = conv.pose_stamped_msg(pose, 5, 'base_link')
    w, x, y, z = pose.quaternion
    o = msg.pose.orientation
    assert (o.x, o.y, o.z, o.w) == (x, y, z, w)
    assert (msg.pose.position.x, msg.pose.position.y, msg.pose.position.z) == (1.0, 2.0, 3.0)
    assert msg.header.frame_id == 'base_link'
    assert conv.pose_from_msg(msg.pose).quaternion[0] == w


@pytest.mark.parametrize('stamp_ns', STAMPS)
def test_time_round_trip(stamp_ns):
    time = conv.time_msg(stamp_ns)
    assert 0 <= time.nanosec < 10 ** 9
    assert conv.stamp_ns_from_header(time) == stamp_ns
    msg = conv.pose_stamped_msg(Pose.identity(), stamp_ns, 'f')
    assert conv.stamp_ns_from_header(msg.header) == stamp_ns


def test_time_out_of_range_and_bad_nanosec_are_named():
    with pytest.raises(ValueError, match='int32'):
        conv.time_msg(2 ** 31 * 10 ** 9)
    bad = SimpleNamespace(stamp=SimpleNamespace(sec=1, nanosec=10 ** 9))
    with pytest.raises(ValueError, match='nanosec'):
        conv.stamp_ns_from_header(bad)


def test_pose_and_transform_round_trips_with_geometry_msgs():
    for i, pose in enumerate(_random_poses(50)):
        stamped = conv.pose_stamped_msg(pose, sim.DEFAULT_START_NS + i, 'base')
        assert isinstance(stamped, PoseStamped)
        _assert_same_pose(conv.pose_from_msg(stamped), pose)
        _assert_same_pose(conv.pose_from_msg(stamped.pose), pose)
        transform = conv.transform_stamped_msg(pose, i, 'tool0', 'camera')
        assert (transform.header.frame_id, transform.child_frame_id) == ('tool0', 'camera')
        _assert_same_pose(conv.pose_from_msg(transform), pose)
        _assert_same_pose(conv.pose_from_msg(transform.transform), pose)
        # Through the middleware's serialisation too.
        wire = deserialize_message(serialize_message(stamped), PoseStamped)
        _assert_same_pose(conv.pose_from_msg(wire), pose)


def test_quaternion_stamped_is_normalised_xyzw():
    msg = conv.quaternion_stamped_msg([2.0, 0.0, 0.0, 2.0], 7, 'tool0')
    q = msg.quaternion
    assert_allclose([q.x, q.y, q.z, q.w], [0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)], atol=1e-15)
    assert msg.header.frame_id == 'tool0' and conv.stamp_ns_from_header(msg.header) == 7


def test_pose_with_covariance_is_read_too():
    msg = PoseWithCovarianceStamped()
    msg.pose.pose.position = Point(x=1.0, y=2.0, z=3.0)
    msg.pose.pose.orientation = Quaternion(x=0.0, y=0.0, z=1.0, w=0.0)
    pose = conv.pose_from_msg(msg)
    assert_array_equal(pose.quaternion, [0.0, 0.0, 0.0, 1.0])


@pytest.mark.parametrize('change, problem', [
    (lambda c: c.__setitem__((0, 0), np.nan), 'NaN or inf'),
    (lambda c: c.__setitem__((0, 1), 1e-7), 'not symmetric'),
    (lambda c: c.__setitem__((2, 2), -1e-6), 'not positive definite (variances must be > 0)'),
    (lambda c: c.__setitem__((3, 3), 5e-324), 'nearly singular: a standard deviation of'),
    (lambda c: c.__setitem__((4, 4), 1e-20), 'nearly singular: a standard deviation of 1e-10'),
    (lambda c: c.__setitem__((slice(0, 2), slice(0, 2)), 1e-6), 'correlations must lie'),
    # one huge entry (symmetric): numpy's eigvalsh failed on it instead
    (lambda c: np.put(c, [2, 12], 1e308), 'correlations must lie'),   # at (0, 2) and (2, 0)
    (lambda c: c.__setitem__((5, 5), 1e308), 'a standard deviation of 1e+154, above 1e+06'),
])
def test_an_unusable_covariance_is_refused_naming_why(change, problem):
    """A subnormal variance passed the Cholesky check and then broke the solver's inverse."""
    covariance = np.eye(6) * 1e-6
    change(covariance)
    msg = PoseWithCovarianceStamped()
    msg.pose.pose.orientation = Quaternion(w=1.0)
    msg.pose.covariance = covariance.ravel().tolist()
    with pytest.raises(conv.BadPoseError, match='pose.covariance: ') as raised:
        conv.pose_from_msg(msg)
    assert problem in str(raised.value) and raised.value.reason == 'bad_covariance'
    assert covariance_problem(np.eye(6) * 1e-18) is None   # 1 nm, 1 nrad: still a sensor


@pytest.mark.parametrize('known', ['position', 'rotation'])
def test_a_covariance_of_one_part_alone_is_unknown_not_bad(known):
    """Only the position's variances (the rotation's zero): every message had been dropped."""
    covariance = np.zeros((6, 6))
    block = slice(0, 3) if known == 'position' else slice(3, 6)
    covariance[block, block] = np.eye(3) * 1e-6
    assert conv.covariance_from_msg(covariance.ravel()) is None
    covariance[0, 5] = covariance[5, 0] = 1e-9   # correlated with the other part: not zero
    with pytest.raises(conv.BadPoseError, match='not positive definite'):
        conv.covariance_from_msg(covariance.ravel())
    covariance[0, 5] = covariance[5, 0] = 0.0
    for bad, problem in ((np.nan, 'NaN or inf'), (-1.0, 'variances must be > 0')):
        covariance[block, block][1, 1] = bad   # the part given must be usable
        with pytest.raises(conv.BadPoseError, match=problem):
            conv.covariance_from_msg(covariance.ravel())


def test_rosbags_messages_read_and_build(typestore):
    poses = _random_poses(20, seed=1)
    cls = typestore.types['geometry_msgs/msg/PoseStamped']
    for i, pose in enumerate(poses):
        built = conv.pose_stamped_msg(pose, sim.DEFAULT_START_NS + i, 'camera', typestore)
        assert isinstance(built, cls)
        # Serialised to CDR (as in a bag) and read back by rosbags.
        raw = typestore.serialize_cdr(built, cls.__msgtype__)
        read = typestore.deserialize_cdr(raw, cls.__msgtype__)
        _assert_same_pose(conv.pose_from_msg(read), pose)
        assert conv.stamp_ns_from_header(read.header) == sim.DEFAULT_START_NS + i
        # rclpy's bytes are rosbags' bytes (what a real `ros2 bag record` would store).
        rclpy_msg = conv.pose_stamped_msg(pose, sim.DEFAULT_START_NS + i, 'camera')
        from_rclpy = typestore.deserialize_cdr(serialize_message(rclpy_msg), cls.__msgtype__)
        _assert_same_pose(conv.pose_from_msg(from_rclpy), pose)
        assert from_rclpy.header.frame_id == 'camera'
    transform = conv.transform_stamped_msg(poses[0], 3, 'tool0', 'camera', typestore)
    assert transform.child_frame_id == 'camera'
    _assert_same_pose(conv.pose_from_msg(transform), poses[0])
    q = conv.quaternion_stamped_msg(poses[0].quaternion, 3, 'tool0', typestore).quaternion
    assert_allclose([q.w, q.x, q.y, q.z], poses[0].quaternion, atol=1e-15)


def test_rosbags_message_made_by_hand(typestore):
    types = typestore.types
    msg = types['geometry_msgs/msg/PoseStamped'](
        header=types['std_msgs/msg/Header'](
            stamp=types['builtin_interfaces/msg/Time'](sec=12, nanosec=34), frame_id='cam'),
        pose=types['geometry_msgs/msg/Pose'](
            position=types['geometry_msgs/msg/Point'](x=0.1, y=0.2, z=0.3),
            orientation=types['geometry_msgs/msg/Quaternion'](x=0.0, y=1.0, z=0.0, w=0.0)))
    pose = conv.pose_from_msg(msg)
    assert_array_equal(pose.position, [0.1, 0.2, 0.3])
    assert_array_equal(pose.quaternion, [0.0, 0.0, 1.0, 0.0])
    assert conv.stamp_ns_from_header(msg.header) == 12_000_000_034


@pytest.mark.parametrize('field, value, message', [
    ('position.x', float('nan'), 'pose.position.x is nan'),
    ('position.z', float('inf'), 'pose.position.z is inf'),
    ('orientation.w', float('-inf'), 'pose.orientation.w is -inf'),
    ('orientation.y', float('nan'), 'pose.orientation.y is nan'),
])
def test_non_finite_numbers_are_named(field, value, message):
    msg = conv.pose_stamped_msg(Pose.identity(), 0, 'f')
    part, axis = field.split('.')
    setattr(getattr(msg.pose, part), axis, value)
    with pytest.raises(conv.BadPoseError, match=message) as error:
        conv.pose_from_msg(msg)
    assert error.value.field == 'pose.' + field
    assert isinstance(error.value, ValueError)


def test_zero_and_far_from_unit_quaternions_are_rejected_with_their_norm():
    msg = conv.pose_stamped_msg(Pose.identity(), 0, 'f')
    msg.pose.orientation.w = 0.0
    with pytest.raises(conv.BadPoseError, match='pose.orientation has norm 0.00'):
        conv.pose_from_msg(msg)
    transform = Transform(translation=Vector3(), rotation=Quaternion(x=0.0, y=0.0, z=0.0, w=2.0))
    with pytest.raises(conv.BadPoseError, match='rotation has norm 2.00') as error:
        conv.pose_from_msg(transform)
    assert error.value.field == 'rotation'
    transform.rotation.w = 1e200   # once printed with its 200 digits
    with pytest.raises(conv.BadPoseError, match=r'rotation has norm 1e\+200; a rotation'):
        conv.pose_from_msg(transform)


def test_slightly_off_unit_quaternions_are_renormalised_within_the_tolerance():
    q = Quaternion(x=0.0, y=0.6, z=0.0, w=0.8 * 1.0005)   # norm 1.0004
    msg = Transform(translation=Vector3(x=1.0), rotation=q)
    pose = conv.pose_from_msg(msg)
    assert_allclose(np.linalg.norm(pose.quaternion), 1.0, atol=1e-15)
    q.w = 0.8 * 1.003                                   # norm 1.0019
    with pytest.raises(conv.BadPoseError, match='rotation has norm 1.0019'):
        conv.pose_from_msg(msg)
    assert_allclose(conv.pose_from_msg(msg, norm_tolerance=0.01).quaternion[0], 0.8 * 1.003
                    / np.hypot(0.6, 0.8 * 1.003))


def test_validate_pose_numbers_directly():
    position, q = conv.validate_pose_numbers([1, 2, 3], (0, 0, 0, 1.0005))
    assert_array_equal(position, [1.0, 2.0, 3.0])
    assert_allclose(q, [0.0, 0.0, 0.0, 1.0], atol=1e-15)
    with pytest.raises(conv.BadPoseError, match='link.y is not a number'):
        conv.validate_pose_numbers([1.0, 'a', 3.0], (0, 0, 0, 1), position_name='link')
    with pytest.raises(conv.BadPoseError, match='3 position and 4 quaternion'):
        conv.validate_pose_numbers([1.0, 2.0], (0, 0, 0, 1))


def test_other_messages_are_a_type_error():
    with pytest.raises(TypeError, match='Vector3'):
        conv.pose_from_msg(Vector3())


def test_module_does_not_import_ros_messages_until_asked(repo_root):
    code = ('import sys, quatcal_ros.ros.conversions; '
            'bad = [m for m in sys.modules if m.split(".")[0] in '
            '("rclpy", "geometry_msgs", "std_msgs", "builtin_interfaces")]; '
            'sys.exit(str(bad) if bad else 0)')
    subprocess.run([sys.executable, '-c', code], check=True, cwd=repo_root)
