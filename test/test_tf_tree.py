"""Tests of stream.tf_tree: chains through the tree, interpolation, FramePoses streams."""

from types import SimpleNamespace

from hypothesis import given, settings
from hypothesis import strategies as st
import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.tf_tree import FramePoses, NEVER, READY, TransformTree, TreeError, WAIT

START_NS = 1_700_000_000 * 10**9
MS = 10**6


def random_pose(rng):
    return Pose(rng.uniform(-1.0, 1.0, 3), quat.normalize(rng.standard_normal(4)))


def assert_same_pose(a, b, atol=1e-12):
    assert_allclose(a.position, b.position, atol=atol)
    assert quat.angle_between(a.quaternion, b.quaternion) < 1e-9


@pytest.fixture
def robot():
    """Build base -> shoulder -> tool (dynamic), base -> camera and tool -> marker (static)."""
    rng = np.random.default_rng(5)
    tree = TransformTree()
    poses = {name: random_pose(rng) for name in ('shoulder', 'tool', 'camera', 'marker')}
    tree.set_transform('base', 'camera', 0, poses['camera'], static=True)
    tree.set_transform('tool', 'marker', 0, poses['marker'], static=True)
    tree.set_transform('base', 'shoulder', START_NS, poses['shoulder'])
    tree.set_transform('shoulder', 'tool', START_NS, poses['tool'])
    return tree, poses


def test_lookup_composes_down_the_tree(robot):
    tree, p = robot
    assert_same_pose(tree.lookup('base', 'marker', START_NS),
                     p['shoulder'] @ p['tool'] @ p['marker'])


def test_lookup_goes_up_to_the_common_ancestor_inverting_edges(robot):
    tree, p = robot
    expected = p['camera'].inverse() @ p['shoulder'] @ p['tool'] @ p['marker']
    assert_same_pose(tree.lookup('camera', 'marker', START_NS), expected)
    assert_same_pose(tree.lookup('marker', 'camera', START_NS), expected.inverse())
    chain = tree.chain('camera', 'marker')
    assert chain.steps == (('camera', True), ('shoulder', False), ('tool', False),
                           ('marker', False))


def test_same_frame_is_the_identity(robot):
    tree, _ = robot
    pose = tree.lookup('tool', 'tool', START_NS)
    assert_same_pose(pose, Pose.identity())


def test_leading_slashes_are_ignored(robot):
    tree, p = robot
    assert_same_pose(tree.lookup('/base', '/camera', 0), p['camera'])


def test_unconnected_frames(robot):
    tree, _ = robot
    tree.set_transform('map', 'odom', START_NS, Pose.identity())
    assert tree.chain('base', 'odom') is None
    with pytest.raises(LookupError, match='not connected'):
        tree.lookup('base', 'odom', START_NS)
    assert tree.chain('base', 'nowhere') is None
    assert tree.disconnection('/tool', 'odom') == ('they are in two separate trees (tool hangs '
                                                   'from root base, odom from root map): no '
                                                   'transform joins them')
    assert tree.disconnection('nowhere', 'tool') == 'nowhere is in no transform received'
    assert tree.disconnection('a', 'b') == 'a and b are in no transform received'


def test_interpolation_is_lerp_and_slerp():
    tree = TransformTree()
    q0 = quat.IDENTITY
    q1 = quat.from_axis_angle([0.0, 0.0, 1.0], np.radians(90.0))
    tree.set_transform('a', 'b', START_NS, Pose(np.zeros(3), q0))
    tree.set_transform('a', 'b', START_NS + 100 * MS, Pose(np.array([1.0, 2.0, 0.0]), q1))
    pose = tree.lookup('a', 'b', START_NS + 25 * MS)
    assert_allclose(pose.position, [0.25, 0.5, 0.0], atol=1e-12)
    expected = quat.from_axis_angle([0.0, 0.0, 1.0], np.radians(22.5))
    assert quat.angle_between(pose.quaternion, expected) < 1e-9


def test_no_extrapolation_and_no_interpolation_across_long_gaps():
    tree = TransformTree(max_gap_ns=50 * MS)
    for k in (0, 10, 200):
        tree.set_transform('a', 'b', START_NS + k * MS, Pose.identity())
    chain = tree.chain('a', 'b')
    assert tree.evaluate(chain, START_NS + 5 * MS)[0] == READY
    assert tree.evaluate(chain, START_NS + 201 * MS)[0] == WAIT
    status, why = tree.evaluate(chain, START_NS + 100 * MS)
    assert status == NEVER and 'gap of 0.19 s' in why and 'a -> b' in why
    assert tree.evaluate(chain, START_NS - 1)[0] == NEVER


def test_buffers_are_bounded():
    tree = TransformTree(cache_ns=1000 * MS, max_length=50)
    for k in range(2000):
        tree.set_transform('a', 'b', START_NS + k * MS, Pose.identity())
    transforms = tree._edges['b'].transforms
    assert len(transforms) == 50 and len(transforms._stamps) < 400
    assert tree.evaluate(tree.chain('a', 'b'), START_NS + 1000 * MS)[0] == NEVER
    # Older than the buffer's time span: not stored, counted.
    tree2 = TransformTree(cache_ns=100 * MS)
    tree2.set_transform('a', 'b', START_NS + 500 * MS, Pose.identity())
    assert not tree2.set_transform('a', 'b', START_NS + 300 * MS, Pose.identity())
    assert tree2.stale['b'] == 1


def test_late_transforms_are_inserted_in_order():
    tree = TransformTree()
    for k in (0, 20, 10):
        tree.set_transform('a', 'b', START_NS + k * MS, Pose(np.array([k, 0.0, 0.0]),
                                                             quat.IDENTITY))
    assert_allclose(tree.lookup('a', 'b', START_NS + 15 * MS).position, [15.0, 0.0, 0.0])


def test_loops_are_refused_and_parents_can_change():
    tree = TransformTree()
    tree.set_transform('a', 'b', 0, Pose.identity(), static=True)
    tree.set_transform('b', 'c', 0, Pose.identity(), static=True)
    with pytest.raises(TreeError, match='loop'):
        tree.set_transform('c', 'a', 0, Pose.identity(), static=True)
    with pytest.raises(TreeError):
        tree.set_transform('a', 'a', 0, Pose.identity())
    tree.set_transform('x', 'c', 0, Pose.identity(), static=True)
    assert tree.parent('c') == 'x' and tree.chain('a', 'c') is None


def test_a_static_edge_sent_on_tf_too_stays_static():
    """As in tf2: the first transform sets an edge's kind; a later one of the other sets it."""
    rng = np.random.default_rng(3)
    tree = TransformTree()
    first, second, moving = random_pose(rng), random_pose(rng), random_pose(rng)
    tree.set_transform('camera', 'optical', 0, first, static=True)
    assert tree.set_transform('camera', 'optical', START_NS, second)   # once, on /tf
    assert tree.is_static('optical')
    for stamp in (START_NS - 10 ** 12, START_NS, START_NS + 10 ** 12):   # at any time
        assert_same_pose(tree.lookup('camera', 'optical', stamp), second)
    tree.set_transform('base', 'camera', START_NS, moving)
    tree.set_transform('base', 'camera', START_NS, moving, static=True)   # then on /tf_static
    assert tree.is_static('camera')


def test_time_jump_back_clears_dynamic_transforms_only(robot):
    tree, p = robot
    generation = tree.generation
    tree.set_transform('base', 'shoulder', START_NS - 10 * 10**9, p['shoulder'])
    assert tree.generation == generation + 1
    assert tree.evaluate(tree.chain('base', 'tool'), START_NS)[0] == WAIT
    assert_same_pose(tree.lookup('base', 'camera', 0), p['camera'])


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(2, 12))
def test_chains_compose_consistently(seed, n_frames):
    """T_a_c = T_a_b @ T_b_c and T_b_a = inv(T_a_b) on random trees."""
    rng = np.random.default_rng(seed)
    tree = TransformTree()
    for child in range(1, n_frames):
        parent = int(rng.integers(0, child))
        tree.set_transform(f'f{parent}', f'f{child}', START_NS, random_pose(rng),
                           static=bool(rng.integers(0, 2)))
    a, b, c = (f'f{i}' for i in rng.integers(0, n_frames, 3))
    ab = tree.lookup(a, b, START_NS)
    assert_same_pose(tree.lookup(a, c, START_NS), ab @ tree.lookup(b, c, START_NS), 1e-9)
    assert_same_pose(tree.lookup(b, a, START_NS), ab.inverse(), 1e-9)


def test_frame_poses_at_each_dynamic_stamp_of_the_chain():
    """Two dynamic edges at different rates: a pose at every stamp of either, in order."""
    rng = np.random.default_rng(8)
    tree = TransformTree()
    tree.set_transform('world', 'base', 0, random_pose(rng), static=True)
    frames = FramePoses(tree, 'world', 'tool')
    unrelated = FramePoses(tree, 'world', 'base')
    out = []
    fast_ms = range(0, 200, 10)      # base -> arm at 100 Hz
    slow_ms = range(5, 200, 25)      # arm -> tool at 40 Hz, other stamps
    events = sorted([(k, 'arm') for k in fast_ms] + [(k, 'tool') for k in slow_ms])
    for k, child in events:
        parent = 'base' if child == 'arm' else 'arm'
        tree.set_transform(parent, child, START_NS + k * MS, random_pose(rng))
        frames.note(child, START_NS + k * MS)
        unrelated.note(child, START_NS + k * MS)
        out += frames.ready()
    stamps = [stamp for stamp, _ in out]
    assert stamps == sorted(set(stamps))
    expected = {START_NS + k * MS for k in list(fast_ms) + list(slow_ms) if 5 <= k <= 180}
    assert set(stamps) == expected
    for stamp, pose in out:
        assert_same_pose(pose, tree.lookup('world', 'tool', stamp))
    assert not unrelated.ready() and unrelated.pending == 0
    assert 'out of order' not in frames.dropped   # two rates in turn: nothing came late
    frames.finish()
    assert frames.dropped['end of recording'] == 1   # 190 ms waits for the next tool stamp


def test_frame_poses_drop_what_can_never_be_evaluated():
    tree = TransformTree(max_gap_ns=20 * MS)
    frames = FramePoses(tree, 'a', 'c')
    tree.set_transform('x', 'y', START_NS, Pose.identity())
    frames.note('y', START_NS)   # elsewhere in the tree: not counted
    tree.set_transform('b', 'c', START_NS, Pose.identity())
    frames.note('c', START_NS)
    assert frames.dropped['frames not connected'] == 1
    tree.set_transform('a', 'b', START_NS, Pose.identity())
    frames.note('b', START_NS)
    assert [stamp for stamp, _ in frames.ready()] == [START_NS]
    tree.set_transform('b', 'c', START_NS + 100 * MS, Pose.identity())
    frames.note('c', START_NS + 100 * MS)
    tree.set_transform('a', 'b', START_NS + 100 * MS, Pose.identity())
    frames.note('b', START_NS + 100 * MS)
    assert [stamp for stamp, _ in frames.ready()] == [START_NS + 100 * MS]
    tree.set_transform('b', 'c', START_NS + 150 * MS, Pose.identity())
    frames.note('c', START_NS + 150 * MS)
    tree.set_transform('a', 'b', START_NS + 200 * MS, Pose.identity())
    frames.note('b', START_NS + 200 * MS)
    assert frames.ready() == []   # 150 ms: a -> b has a 100 ms gap; 200 ms: b -> c waits
    assert frames.dropped['not evaluable'] == 1 and 'a -> b: gap' in frames.last_dropped
    assert frames.pending == 1


def test_frame_poses_count_a_transform_that_came_too_late():
    """A transform older than the last pose composed was dropped without a count."""
    tree = TransformTree()
    frames = FramePoses(tree, 'a', 'b')
    for k in (0, 10, 30, 20, 40):   # 20 ms after 30 ms: out of order
        tree.set_transform('a', 'b', START_NS + k * MS, Pose.identity())
        frames.note('b', START_NS + k * MS)
        frames.ready()
    assert frames.dropped == {'out of order': 1}
    assert frames.last_dropped == ('a transform to b came 10 ms older than the last a -> b pose '
                                   'composed')


def test_frame_poses_restart_after_a_time_jump():
    tree = TransformTree()
    frames = FramePoses(tree, 'a', 'b')
    for stamp in (START_NS, START_NS + 10 * MS, START_NS - 60 * 10**9):
        tree.set_transform('a', 'b', stamp, Pose.identity())
        frames.note('b', stamp)
        assert [s for s, _ in frames.ready()] == [stamp]


def test_tf_transforms_get_the_pose_topics_checks():
    """Stamps against the node clock, implausible positions, empty frame ids: counted, skipped."""
    from quatcal_ros.ros.conversions import transform_stamped_msg
    from quatcal_ros.ros.pose_screen import PoseScreen
    from quatcal_ros.ros.tf_feed import TfFeed
    from quatcal_ros.stream.message_checks import CheckConfig
    from tf2_msgs.msg import TFMessage
    screen = PoseScreen(CheckConfig(max_stamp_offset_ns=30 * 10**9, max_position_m=1000.0))
    poses = []
    feed = TfFeed(TfFeed.new_tree(), screen, {'link_pose': ('base', 'tool')},
                  lambda stream, stamp_ns, pose: poses.append(stamp_ns))
    now = START_NS
    near = Pose(np.array([0.1, 0.2, 0.3]), quat.IDENTITY)
    far = Pose(np.array([5000.0, 0.0, 0.0]), quat.IDENTITY)
    day = 86_400 * 10**9
    sent = [(near, now + day, 'base', 'tool'), (near, now - day, 'base', 'tool'),
            (far, now, 'base', 'tool'), (near, now, 'base', ''), (near, now, '', 'tool'),
            (near, now, 'base', 'tool'), (near, now + 10 * MS, 'base', 'tool')]
    for pose, stamp, parent, child in sent:
        feed.take('/tf', TFMessage(transforms=[transform_stamped_msg(pose, stamp, parent, child)]),
                  False, now)
    assert dict(screen.stats.bad) == {
        ('/tf', 'stamp_in_future'): 1, ('/tf', 'stamp_in_past'): 1,
        ('/tf', 'implausible_position'): 1, ('/tf', 'breaks_tree'): 2}
    assert feed.tree.frames == {'base', 'tool'} and feed.tree.generation == 0   # no time jump
    assert poses == [now, now + 10 * MS]
    # Offline (the replay: no node clock) only the stamp's own checks apply.
    feed.take('/tf', TFMessage(transforms=[transform_stamped_msg(near, now + 10**15, 'base',
                                                                 'tool')]), False)
    assert poses[-1] == now + 10**15


def test_a_kept_static_edge_keeps_its_first_value():
    """The replay's first pass over /tf_static: each edge's first value holds from the start."""
    tree = TransformTree()
    first, second = Pose(np.ones(3), quat.IDENTITY), Pose(np.zeros(3), quat.IDENTITY)
    assert tree.set_transform('a', 'b', 0, first, static=True, keep=True)
    assert tree.set_transform('x', 'b', 5, second, static=True, keep=True)   # kept: a -> b
    assert tree.parent('b') == 'a'
    np.testing.assert_array_equal(tree.lookup('a', 'b', 0).position, first.position)
    tree.set_transform('a', 'b', 5, second, static=True)   # where the bag sends it again
    np.testing.assert_array_equal(tree.lookup('a', 'b', 0).position, second.position)


def test_link_frames_given_the_wrong_way_round_are_named():
    """The pose composes (its inverse): the node advised eye_to_hand, not the frames."""
    from quatcal_ros.ros.pose_screen import PoseScreen
    from quatcal_ros.ros.tf_feed import TfFeed
    tree = TfFeed.new_tree()
    turn = Pose(np.array([0.1, 0.2, 0.3]), quat.IDENTITY)
    tree.set_transform('base_link', 'shoulder', START_NS, turn)
    tree.set_transform('shoulder', 'tool0', START_NS, turn)
    tree.set_transform('camera', 'marker', START_NS, turn)
    frames = {'link_pose': ('tool0', 'base_link'), 'sensor_pose': ('marker', 'camera')}
    feed = TfFeed(tree, PoseScreen(), frames, lambda *pose: None, link='link_pose')
    # (the link frames' stays whatever the estimate: no robot hangs its base below its tool)
    assert feed.problems(SimpleNamespace(warnings=[], usable=True, samples=9)) == \
        feed.problems() == [
        'TF input: the link frames look swapped: the base frame given, tool0, hangs below the '
        'effector frame given, base_link, in the TF tree; a link pose is the effector in the '
        'robot base frame (base base_link, effector tool0?)']   # (not the sensor's frames)
    right = TfFeed(tree, PoseScreen(), {'link_pose': ('base_link', 'tool0')}, lambda *pose: None,
                   link='link_pose')
    assert right.problems() == []


def test_tracking_frames_given_the_wrong_way_round_are_named():
    # The inverse composed: the node stood at 'no still sample' (the inverse's positions take
    # the rotation noise times the distance) and then advised invert_sensor.
    from quatcal_ros.ros.pose_screen import PoseScreen
    from quatcal_ros.ros.tf_feed import TfFeed
    tree = TfFeed.new_tree()
    turn = Pose(np.array([0.1, 0.2, 0.3]), quat.IDENTITY)
    tree.set_transform('camera_link', 'camera_optical', START_NS, turn, static=True)
    tree.set_transform('camera_optical', 'aruco_marker', START_NS, turn)
    frames = {'link_pose': ('base_link', 'tool0'),
              'sensor_pose': ('aruco_marker', 'camera_optical')}
    feed = TfFeed(tree, PoseScreen(), frames, lambda *pose: None, link='link_pose',
                  sensor='sensor_pose')
    assert feed.swapped_frames() == [
        'TF input: the tracking frames look swapped: the camera frame given, aruco_marker, '
        'hangs below the marker frame given, camera_optical, in the TF tree; a sensor pose is '
        'the marker in the camera frame (tracking_base_frame camera_optical, '
        'tracking_marker_frame aruco_marker?), unless the detector publishes the camera under '
        'the marker on purpose']
    right = TfFeed(tree, PoseScreen(), {'sensor_pose': ('camera_optical', 'aruco_marker')},
                   lambda *pose: None, sensor='sensor_pose')
    assert right.swapped_frames() == []
    # A detector that publishes the camera under the marker on purpose: once an estimate fits
    # the sensor poses as composed (no frame-convention warning), it is not said; while the
    # estimate says another convention fits far better, it stays.
    fits = SimpleNamespace(warnings=['the motions are small'], usable=True, samples=5)
    assert feed.swapped_frames(fits) == []
    misfit = SimpleNamespace(warnings=['frame convention: the samples fit badly as configured'],
                             usable=False, samples=5)
    assert len(feed.swapped_frames(misfit)) == 1
    # Nor from an estimate not to use (a fit that is no rigid mounting), or from too few
    # samples for the convention check to tell (3: it never warned).
    assert len(feed.swapped_frames(SimpleNamespace(warnings=[], usable=False,
                                                   samples=9))) == 1
    assert len(feed.swapped_frames(SimpleNamespace(warnings=[], usable=True, samples=4))) == 1
    assert feed.swapped_frames(None) == feed.swapped_frames()


def test_frames_without_some_edges_are_those_the_other_edges_hold():
    # The frames a TF input names as seen leave out the node's own broadcast and a journal's.
    tree = TransformTree()
    tree.set_transform('base_link', 'tool0', 0, Pose.identity())
    tree.set_transform('tool0', 'camera_link', 0, Pose.identity(), static=True)   # ours
    tree.set_transform('camera_link', 'optical', 0, Pose.identity(), static=True)
    everything = {'base_link', 'tool0', 'camera_link', 'optical'}
    assert tree.frames_without(set()) == tree.frames == everything
    assert tree.frames_without({'camera_link'}) == everything   # (held by other edges)
    assert tree.frames_without({'camera_link', 'optical'}) == {'base_link', 'tool0'}
