"""Tests of quatcal_ros.ros.cdr: poses from raw CDR bytes equal rosbags' and conversions' own."""

import struct

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
import pytest

from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import MAX_POSITION_M
from quatcal_ros.ros import cdr, conversions
from quatcal_ros.ros.bag import TYPESTORE

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TRANSFORM_STAMPED = 'geometry_msgs/msg/TransformStamped'
TYPES = (POSE_STAMPED, TRANSFORM_STAMPED)
NS = 1_000_000_000


def message(msgtype, pose, stamp_ns, frame_id='base', child_frame_id='tool0'):
    if msgtype == POSE_STAMPED:
        return conversions.pose_stamped_msg(pose, stamp_ns, frame_id, typestore=TYPESTORE)
    return conversions.transform_stamped_msg(pose, stamp_ns, frame_id, child_frame_id,
                                             typestore=TYPESTORE)


def raw(msgtype, msg, little_endian=True):
    return bytes(TYPESTORE.serialize_cdr(msg, msgtype, little_endian=little_endian))


def random_raws(rng, msgtype, count, frame_id='base', child_frame_id='tool0'):
    poses = [Pose.create(rng.uniform(-2.0, 2.0, 3), rng.standard_normal(4))
             for _ in range(count)]
    stamps = rng.integers(-2**31 * NS, (2**31 - 1) * NS, count)
    return [raw(msgtype, message(msgtype, pose, int(stamp), frame_id, child_frame_id))
            for pose, stamp in zip(poses, stamps)]


def by_rosbags(msgtype, data):
    """(stamp, Pose) as the replay's one-message path reads it; raises what it raises."""
    msg = TYPESTORE.deserialize_cdr(data, msgtype)
    return conversions.stamp_ns_from_header(msg.header), conversions.pose_from_msg(msg)


def assert_rows_equal_rosbags(msgtype, raws, decoded):
    """
    Every decoded row is bit for bit what rosbags and conversions make of its message.

    The one-message decoder (the live node's) vouches for the same rows, with the same numbers
    and the message's header frame id; cdr.frame_ids reads its frames as conversions does.
    """
    for k in np.flatnonzero(decoded.ok):
        stamp_ns, pose = by_rosbags(msgtype, raws[k])
        assert int(decoded.stamps_ns[k]) == stamp_ns
        assert np.array_equal(decoded.positions[k], pose.position)
        assert np.array_equal(decoded.quaternions[k], pose.quaternion)
    for k, data in enumerate(raws):
        single = cdr.decode_pose(data, msgtype)
        pose = None if single is None else conversions.pose_from_values(*single[2])
        # Zero stamps and far positions are the message checks' to judge (decode_poses
        # leaves them to the slow path; decode_pose's caller checks them).
        judged = pose is not None and (single[0] == 0
                                       or np.abs(pose.position).max() > MAX_POSITION_M)
        assert (pose is not None) == bool(decoded.ok[k]) or judged, k
        if judged:
            continue
        if pose is not None:
            msg = TYPESTORE.deserialize_cdr(data, msgtype)
            assert single[0] == decoded.stamps_ns[k] and single[1] == msg.header.frame_id
            assert cdr.frame_ids(data, msgtype) == conversions.frame_ids(msg)
            assert np.array_equal(pose.position, decoded.positions[k])
            assert np.array_equal(pose.quaternion, decoded.quaternions[k])


@pytest.mark.parametrize('msgtype', TYPES)
def test_frame_ids_of_every_length_and_so_every_alignment(msgtype):
    rng = np.random.default_rng(1)
    children = range(10) if msgtype == TRANSFORM_STAMPED else [5]
    for length in range(18):
        for child_length in children:
            raws = random_raws(rng, msgtype, 4, 'f' * length, 'c' * child_length)
            decoded = cdr.decode_poses(raws, msgtype)
            assert decoded.ok.all(), (length, child_length)
            assert_rows_equal_rosbags(msgtype, raws, decoded)


@pytest.mark.parametrize('msgtype', TYPES)
def test_messages_of_several_layouts_in_one_run(msgtype):
    rng = np.random.default_rng(2)
    raws = [data for frame_id in ('base', 'base_link_long_name', '', 'world')
            for data in random_raws(rng, msgtype, 3, frame_id)]
    raws = [raws[k] for k in rng.permutation(len(raws))]
    decoded = cdr.decode_poses(raws, msgtype)
    assert decoded.ok.all()   # 'base' and 'world': the same size, not the same strings
    assert_rows_equal_rosbags(msgtype, raws, decoded)


def test_renormalised_quaternions_equal_conversions():
    msg = message(POSE_STAMPED, Pose.identity(), 5 * NS)
    orientation = msg.pose.orientation
    orientation.x, orientation.y, orientation.z, orientation.w = 0.1, -0.2, 0.3, 0.9268
    slightly_off = raw(POSE_STAMPED, msg)   # norm 0.99948
    decoded = cdr.decode_poses([slightly_off] * 8, POSE_STAMPED)
    assert decoded.ok.all()
    assert_rows_equal_rosbags(POSE_STAMPED, [slightly_off] * 8, decoded)
    assert np.linalg.norm(decoded.quaternions[0]) == pytest.approx(1.0, abs=1e-15)


def odd_messages():
    """(why, raw PoseStamped) that the decoder must leave to rosbags and conversions."""
    good = message(POSE_STAMPED, Pose.create([1.0, 2.0, 3.0], [1.0, 0.0, 0.0, 0.0]), 7 * NS)
    data = raw(POSE_STAMPED, good)
    frame_length_at = 12
    odd = {
        'big endian': raw(POSE_STAMPED, good, little_endian=False),
        'not CDR': b'\x01\x01' + data[2:],
        'cut short': data[:-8],
        'trailing bytes': data + b'\x00' * 4,
        'string length': data[:frame_length_at] + struct.pack('<I', 4) + data[16:],
        'string too long': data[:frame_length_at] + struct.pack('<I', 4000) + data[16:],
        'no terminator': data[:20] + b'x' + data[21:],   # 'base\0' -> 'basex'
        'not ascii': data[:16] + 'bäs'.encode() + data[20:],
        'not utf-8': data[:16] + b'\xff\xfe\xfd\xfc' + data[20:],
    }
    for name, field, value in (('nan position', 'position', float('nan')),
                               ('inf position', 'position', float('inf')),
                               ('zero quaternion', 'orientation', 0.0),
                               ('non-unit quaternion', 'orientation', 0.6)):
        msg = message(POSE_STAMPED, Pose.identity(), 7 * NS)
        target = getattr(msg.pose, field)
        target.x = target.y = target.z = value
        if name == 'zero quaternion':
            target.w = 0.0
        odd[name] = raw(POSE_STAMPED, msg)
    msg = message(POSE_STAMPED, Pose.identity(), 7 * NS)
    msg.header.stamp.nanosec = 1_500_000_000
    odd['nanosec out of range'] = raw(POSE_STAMPED, msg)
    return data, odd


@pytest.mark.parametrize('why', sorted(odd_messages()[1]))
def test_anything_odd_is_left_to_rosbags(why):
    good, odd = odd_messages()
    for run in ([odd[why]], [good, odd[why], good], [odd[why]] * 3 + [good]):
        decoded = cdr.decode_poses(run, POSE_STAMPED)
        assert decoded.ok.tolist() == [data is good for data in run], why
        assert_rows_equal_rosbags(POSE_STAMPED, run, decoded)


def test_up_to_three_padding_bytes_are_read_as_rosbags_reads_them():
    rng = np.random.default_rng(3)
    raws = [data + b'\x00' * (k % 4) for k, data in
            enumerate(random_raws(rng, POSE_STAMPED, 8))]
    decoded = cdr.decode_poses(raws, POSE_STAMPED)
    assert decoded.ok.all()
    assert_rows_equal_rosbags(POSE_STAMPED, raws, decoded)


def test_no_messages():
    decoded = cdr.decode_poses([], TRANSFORM_STAMPED)
    assert decoded.ok.shape == (0,) and decoded.positions.shape == (0, 3)
    assert decoded.quaternions.shape == (0, 4)


@settings(max_examples=300, deadline=None)
@given(msgtype=st.sampled_from(TYPES), seed=st.integers(0, 2**32 - 1),
       frame_id=st.text(max_size=12), child_frame_id=st.text(max_size=12),
       changes=st.lists(st.tuples(st.integers(0, 120), st.integers(0, 255)), max_size=4))
def test_a_decoded_row_is_always_what_rosbags_reads(msgtype, seed, frame_id, child_frame_id,
                                                    changes):
    """Damaged bytes: whatever the decoder vouches for, rosbags reads to the same numbers."""
    rng = np.random.default_rng(seed)
    raws = random_raws(rng, msgtype, 3, frame_id, child_frame_id)
    damaged = bytearray(raws[1])
    for at, value in changes:
        if at < len(damaged):
            damaged[at] = value
    raws[1] = bytes(damaged)
    decoded = cdr.decode_poses(raws, msgtype)
    if frame_id.isascii() and child_frame_id.isascii():
        assert decoded.ok[0] and decoded.ok[2]
    assert_rows_equal_rosbags(msgtype, raws, decoded)


@pytest.mark.parametrize('msgtype', TYPES)
def test_one_message_from_rclpy_decodes_as_rclpy_reads_it(msgtype):
    """The live node's raw subscriptions get rclpy's bytes: read to rclpy's own numbers."""
    from geometry_msgs.msg import PoseStamped, TransformStamped
    from rclpy.serialization import deserialize_message, serialize_message

    kind = PoseStamped if msgtype == POSE_STAMPED else TransformStamped
    rng = np.random.default_rng(4)
    for frame_id in ('', 'b', 'base_link', 'world_frame_x'):
        msg = kind()
        msg.header.frame_id = frame_id
        msg.header.stamp.sec, msg.header.stamp.nanosec = int(rng.integers(-2**31, 2**31)), 999
        values = rng.uniform(-2.0, 2.0, 7)
        if kind is PoseStamped:
            target, position = msg.pose.orientation, msg.pose.position
        else:
            msg.child_frame_id = 'tool' * len(frame_id)
            target, position = msg.transform.rotation, msg.transform.translation
        position.x, position.y, position.z = values[:3]
        target.x, target.y, target.z, target.w = values[3:] / np.linalg.norm(values[3:])
        stamp_ns, frame, numbers = cdr.decode_pose(serialize_message(msg), msgtype)
        again = deserialize_message(serialize_message(msg), kind)
        assert stamp_ns == conversions.stamp_ns_from_header(again.header)
        assert frame == frame_id
        pose, expected = conversions.pose_from_values(*numbers), conversions.pose_from_msg(again)
        assert np.array_equal(pose.position, expected.position)
        assert np.array_equal(pose.quaternion, expected.quaternion)
