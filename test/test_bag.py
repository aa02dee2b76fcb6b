"""Tests of quatcal_ros.ros.bag: reading rosbag2 recordings and replaying them into a Session."""

import re
import sqlite3

import numpy as np
from numpy.testing import assert_allclose
import pytest

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.ros import bag, cdr, conversions
from quatcal_ros.ros.bag import Bag, BagError, PoseInput, Replay, TYPESTORE, write_bag
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.sim import simulation as sim
from quatcal_ros.stream.message_checks import CheckConfig
from quatcal_ros.stream.session import Session
from rosbags.rosbag2 import Writer

POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
TRANSFORM_STAMPED = 'geometry_msgs/msg/TransformStamped'
TOPICS = {'/link': POSE_STAMPED, '/sensor': POSE_STAMPED}
MS = 1_000_000
DECODE_POSES = cdr.decode_poses


@pytest.fixture(scope='module')
def streams():
    rng = np.random.default_rng(40)
    cell = sim.random_cell(rng)
    return sim.stop_and_go_streams(rng, cell, 6, link_rate_hz=200.0, rotation_noise_deg=0.2,
                                   translation_noise_m=0.001)


def pose_messages(streams, link_type=POSE_STAMPED):
    """(topic, log time, message) of both streams, in log-time order (sensor frames late)."""
    if link_type == POSE_STAMPED:
        link = [('/link', stamp + MS, conversions.pose_stamped_msg(pose, stamp, 'base',
                                                                   typestore=TYPESTORE))
                for stamp, pose in streams.link]
    else:
        link = [('/link', stamp + MS, conversions.transform_stamped_msg(
            pose, stamp, 'base', 'tool0', typestore=TYPESTORE)) for stamp, pose in streams.link]
    sensor = [('/sensor', delivered, conversions.pose_stamped_msg(pose, stamp, 'camera',
                                                                  typestore=TYPESTORE))
              for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    return sorted(link + sensor, key=lambda message: message[1])


@pytest.fixture(scope='module')
def pose_bag(tmp_path_factory, streams):
    path = tmp_path_factory.mktemp('bags') / 'poses'
    write_bag(path, TOPICS, pose_messages(streams))
    return path


def replay(path, link='/link', sensor='/sensor', session=None, partial=False, **options):
    session = session or Session()
    with Bag(path) as recording:
        report = Replay(recording, PoseInput(link), PoseInput(sensor), **options).run(
            session, partial=partial)
    return session, report


@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_write_and_read_back(tmp_path, streams, storage):
    messages = pose_messages(streams)
    write_bag(tmp_path / 'b', TOPICS, messages, storage)
    with Bag(tmp_path / 'b') as recording:
        assert recording.topics == {'/link': (POSE_STAMPED, len(streams.link)),
                                    '/sensor': (POSE_STAMPED, len(streams.sensor))}
        assert recording.message_count == len(messages)
        read = list(recording.messages(recording.connections({'/link', '/sensor'})))
    assert [log_ns for _, log_ns, _ in read] == [log_ns for _, log_ns, _ in messages]
    first = TYPESTORE.deserialize_cdr(read[0][2], POSE_STAMPED)
    assert conversions.stamp_ns_from_header(first.header) == streams.link[0][0]


def test_replay_is_the_session_fed_in_log_order(pose_bag, streams):
    """No second pipeline: the replay gives what the same poses fed by hand give."""
    session, report = replay(pose_bag)
    by_hand = Session()
    fed = [(stamp + MS, 0, stamp, pose) for stamp, pose in streams.link]
    fed += [(delivered, 1, stamp, pose)
            for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    for _, stream, stamp, pose in sorted(fed, key=lambda m: m[:2]):
        (by_hand.add_link_pose if stream == 0 else by_hand.add_sensor_pose)(stamp, pose)
    assert session.counters == by_hand.counters
    assert session.counters['samples'] == 6
    session.estimate()
    by_hand.estimate()
    # Equal but for the last bit of the poses' round trip through messages (renormalised).
    assert_allclose(session.result.quaternion, by_hand.result.quaternion, atol=1e-12)
    assert report.messages == len(streams.link) + len(streams.sensor)
    assert report.warnings() == []
    assert report.frames == {'link': ('base', None), 'sensor': ('camera', None)}
    assert report.stamps['sensor'] == [streams.sensor[0][0], streams.sensor[-1][0]]


def test_transform_stamped_and_result_frames(tmp_path, streams):
    write_bag(tmp_path / 'b', {'/link': TRANSFORM_STAMPED, '/sensor': POSE_STAMPED},
              pose_messages(streams, TRANSFORM_STAMPED), 'mcap')
    session, report = replay(tmp_path / 'b')
    assert session.counters['samples'] == 6
    assert bag.result_frames(report) == ('tool0', 'camera')
    assert bag.result_frames(report, 'eye_to_hand') == ('base', 'camera')
    assert bag.result_frames(report, invert_sensor=True) == ('tool0', None)


def test_progress_is_reported(pose_bag):
    seen = []
    with Bag(pose_bag) as recording:
        Replay(recording, PoseInput('/link'), PoseInput('/sensor')).run(Session(), seen.append)
    assert seen and seen == sorted(seen) and not seen[0] % bag.PROGRESS_EVERY


def test_bad_messages_are_counted_and_skipped(tmp_path, streams):
    messages = pose_messages(streams)
    links = [i for i, m in enumerate(messages) if m[0] == '/link']
    nan, zero, stamp = links[10], links[20:23], links[30]
    messages[nan][2].pose.position.x = float('nan')
    for i in zero:
        orientation = messages[i][2].pose.orientation
        orientation.x = orientation.y = orientation.z = orientation.w = 0.0
    messages[stamp][2].header.stamp.nanosec = 2_000_000_000
    write_bag(tmp_path / 'b', TOPICS, messages)
    session, report = replay(tmp_path / 'b')
    # Counted as the live node counts them: per stream and reason (message_checks.REASONS).
    assert report.bad == {('link_pose', 'non_finite'): 1, ('link_pose', 'zero_quaternion'): 3,
                          ('link_pose', 'bad_stamp'): 1}
    warnings = report.warnings()
    assert '/link: 3 message(s) skipped (zero_quaternion): pose.orientation has norm 0' \
        in '\n'.join(warnings)
    assert '/link: 1 message(s) skipped (non_finite): pose.position.x' in '\n'.join(warnings)
    assert session.counters['link_messages'] == len(streams.link) - 5
    assert session.counters['samples'] == 6


def test_undecodable_and_late_messages(tmp_path, streams):
    path = tmp_path / 'b'
    with Writer(path, version=8) as writer:
        link = writer.add_connection('/link', POSE_STAMPED, typestore=TYPESTORE)
        sensor = writer.add_connection('/sensor', POSE_STAMPED, typestore=TYPESTORE)
        for topic, log_ns, msg in pose_messages(streams):
            connection = link if topic == '/link' else sensor
            writer.write(connection, log_ns, TYPESTORE.serialize_cdr(msg, POSE_STAMPED))
        writer.write(link, 4 * 10**18, b'\x00\x01not a message')
        late = conversions.pose_stamped_msg(streams.link[-1][1], streams.link[-1][0] - 20 * MS,
                                            'base', typestore=TYPESTORE)
        writer.write(link, 4 * 10**18 + 1, TYPESTORE.serialize_cdr(late, POSE_STAMPED))
    _, report = replay(path)
    assert report.bad == {('link_pose', 'undecodable'): 1, ('link_pose', 'out_of_order'): 1}
    assert any('/link: 1 message(s) skipped (out_of_order): stamp 20 ms older' in w
               for w in report.warnings())


def test_a_number_where_a_db3_holds_a_message_is_undecodable(tmp_path, streams):
    # sqlite's columns take any type: a hand-edited or damaged db3 gave an int for the bytes,
    # and replay raised a TypeError.
    path = tmp_path / 'b'
    write_bag(path, TOPICS, pose_messages(streams), 'sqlite3')
    (db,) = path.glob('*.db3')
    with sqlite3.connect(db) as connection:
        connection.execute('update messages set data=12345 where id=500')
        connection.execute('update messages set data=1.5 where id=501')
    connection.close()
    _, report = replay(path)
    assert sum(count for (_, reason), count in report.bad.items()
               if reason == 'undecodable') == 2, report.bad


@pytest.mark.parametrize('cut', [1, 8, 50])
def test_a_db3_cut_inside_its_last_page_is_damaged(tmp_path, streams, cut):
    # sqlite read the torn page without a word, zeros for the missing bytes: a pose of the
    # last messages came out 3.9 deg off and was used.
    path = tmp_path / 'b'
    write_bag(path, TOPICS, pose_messages(streams), 'sqlite3')
    (db,) = path.glob('*.db3')
    db.write_bytes(db.read_bytes()[:-cut])
    with pytest.raises(BagError, match=r'the recording is damaged after \d+ messages: b.db3 ends '
                                       r'inside a page \(\d+ bytes, pages of \d+\): it was cut '
                                       'short, and its last messages may be corrupt'):
        replay(path)
    _, report = replay(path, partial=True)
    assert report.warnings()[0].startswith('partial replay: the recording is damaged (')
    assert 'metadata.yaml' not in report.warnings()[0]
    # With a static TF topic, read first in a pass of its own: the damage was raised after
    # that pass, and a partial replay read nothing else.
    static = tf_message([conversions.transform_stamped_msg(Pose.identity(), 0, 'a', 'b',
                                                           typestore=TYPESTORE)])
    write_bag(tmp_path / 'tf', {**TOPICS, '/tf_static': bag.TF_TYPE},
              [('/tf_static', 1, static), *pose_messages(streams)], 'sqlite3')
    (db,) = (tmp_path / 'tf').glob('*.db3')
    db.write_bytes(db.read_bytes()[:-cut])
    (db.parent / 'copy.db3').write_bytes(db.read_bytes()[:100])   # (not in the index)
    session = Session()
    with Bag(tmp_path / 'tf') as recording:
        report = Replay(recording, PoseInput('/link'), PoseInput('/sensor'),
                        tf_topics=('/tf_static',)).run(session, partial=True)
    # (every message read; the torn one among the last may be refused, as bad)
    assert session.counters['link_messages'] >= len(streams.link) - 1 and not report.unread
    assert re.search(r'after \d+ messages: tf.db3 ends inside a page', report.damaged)


def tf_message(transforms):
    return TYPESTORE.types[bag.TF_TYPE](transforms=transforms)


def test_tf_frames_with_static_transforms_anywhere_in_the_bag(tmp_path, streams):
    """Link pose base_link -> tool0 through a static base_link -> robot_base."""
    rng = np.random.default_rng(41)
    mount = Pose(rng.uniform(-1, 1, 3), sim.random_quaternions(rng, 1)[0])
    messages = [('/tf', stamp + MS, tf_message([conversions.transform_stamped_msg(
        pose, stamp, '/robot_base', 'tool0', typestore=TYPESTORE)]))
        for stamp, pose in streams.link]
    messages += [m for m in pose_messages(streams) if m[0] == '/sensor']
    static = tf_message([conversions.transform_stamped_msg(mount, 0, 'base_link', 'robot_base',
                                                           typestore=TYPESTORE)])
    messages = sorted(messages, key=lambda m: m[1])
    messages.insert(len(messages) // 2, ('/tf_static', messages[len(messages) // 2][1], static))
    write_bag(tmp_path / 'b', {'/tf': bag.TF_TYPE, '/tf_static': bag.TF_TYPE,
                               '/sensor': POSE_STAMPED}, messages, 'mcap')
    session = Session()
    with Bag(tmp_path / 'b') as recording:
        report = Replay(recording, PoseInput(frames=('base_link', 'tool0')),
                        PoseInput('/sensor')).run(session)
    assert session.counters['link_messages'] == len(streams.link)
    assert session.counters['samples'] == 6
    assert report.frames['link'] == ('base_link', 'tool0')
    assert report.warnings() == []
    # A static base frame turns every link pose alike: the motions, so the answer, are kept.
    session.estimate()
    error = np.degrees(quat.angle_between(session.result.quaternion, streams.truth.quaternion))
    assert error < 3 * session.result.uncertainty_deg


def test_a_stale_last_message_is_counted_bad_and_every_other_one_good(tmp_path, streams):
    # The last link message stamped 10 s behind its stream: the session held it for the next
    # message to say stale or time jump, none came, and it was counted neither good nor bad.
    messages = pose_messages(streams)
    stamp, pose = streams.link[-1]
    stale = conversions.pose_stamped_msg(pose, stamp - 10 * 10**9, 'base', typestore=TYPESTORE)
    messages.append(('/link', messages[-1][1] + MS, stale))
    write_bag(tmp_path / 'b', TOPICS, messages)
    session, report = replay(tmp_path / 'b')
    assert report.bad == {('link_pose', 'stale_stamp'): 1}
    assert 'the recording ended after it: a stale message' in \
        report.examples[('link_pose', 'stale_stamp')]
    assert report.good == {'link_pose': len(streams.link), 'sensor_pose': len(streams.sensor)}
    assert session.counters['rejected'] == 1


def test_a_held_pose_is_counted_once_when_the_session_decides(streams):
    # A link pose 10 s behind its stream waits for the next message: counted good at once, it
    # was counted bad again when the next one showed it stale (and that next one not at all).
    session, screen = Session(), PoseScreen()
    link = [(stamp, pose) for stamp, pose in streams.link[:50]]

    def give(stamp, pose):
        return screen.verdict('link_pose', session.add_link_pose(stamp, pose),
                              held=session.held)

    def see(stamp):
        return screen.verdict('sensor_pose', session.add_sensor_pose(stamp, Pose.identity()),
                              held=session.held)
    for stamp, pose in link[:30]:
        give(stamp, pose)
        see(stamp)
    give(link[29][0] - 10 * 10**9, link[29][1])
    assert screen.stats.good['link_pose'] == 30 and session.held == {'link_pose'}
    assert not screen.stats.bad
    give(*link[30])   # the stream goes on: the held pose was stale
    assert screen.stats.bad == {('link_pose', 'stale_stamp'): 1}
    assert screen.stats.good['link_pose'] == 31 and not session.held
    # Held again, then a sensor pose far behind too: a time jump both streams agree on, and
    # the held pose is good after all.
    give(link[30][0] - 20 * 10**9, link[30][1])
    assert screen.stats.good['link_pose'] == 31
    see(link[30][0] - 20 * 10**9)
    assert screen.stats.good == {'link_pose': 32, 'sensor_pose': 31} and not session.held
    assert session.counters['time_jumps'] == 1


def test_a_zero_stamped_transform_on_tf_is_counted_and_skipped(tmp_path, streams):
    # It was composed into a link pose at stamp 0: the tree took it for a time jump back,
    # cleared its buffers and the session restarted pairing ('time jumped back 1 time(s)').
    messages = [('/tf', stamp + MS, tf_message([conversions.transform_stamped_msg(
        pose, stamp, 'base_link', 'tool0', typestore=TYPESTORE)]))
        for stamp, pose in streams.link]
    middle = len(messages) // 2
    messages.insert(middle, ('/tf', messages[middle][1], tf_message([
        conversions.transform_stamped_msg(streams.link[middle][1], 0, 'base_link', 'tool0',
                                          typestore=TYPESTORE)])))
    messages += [m for m in pose_messages(streams) if m[0] == '/sensor']
    write_bag(tmp_path / 'b', {'/tf': bag.TF_TYPE, '/sensor': POSE_STAMPED},
              sorted(messages, key=lambda m: m[1]), 'mcap')
    session = Session()
    with Bag(tmp_path / 'b') as recording:
        report = Replay(recording, PoseInput(frames=('base_link', 'tool0')),
                        PoseInput('/sensor')).run(session)
    assert report.bad == {('/tf', 'zero_stamp'): 1}
    assert session.counters['link_messages'] == len(streams.link)
    assert session.counters['samples'] == 6
    assert not any('time jumped back' in w for w in report.warnings())


def test_opening_errors_name_the_file(tmp_path):
    with pytest.raises(BagError, match='no such file or directory'):
        Bag(tmp_path / 'missing')
    (tmp_path / 'dir').mkdir()
    with pytest.raises(BagError, match='dir: not a rosbag2 directory: no metadata.yaml and no '
                                       r'.db3 or .mcap file in it; it is empty$'):
        Bag(tmp_path / 'dir')
    # A storage file without its index: the recorder was killed, and the advice is to reindex
    # (it was given for folders that held no recording at all).
    (tmp_path / 'dir' / 'run_0.mcap').write_bytes(b'')
    with pytest.raises(BagError, match=r'dir: not a rosbag2 directory \(no metadata.yaml in '
                                       r'it\); if the recorder was killed, `ros2 bag reindex`'):
        Bag(tmp_path / 'dir')
    (tmp_path / 'file.txt').write_text('hello')
    with pytest.raises(BagError, match='file.txt: not a rosbag2 directory'):
        Bag(tmp_path / 'file.txt')
    (tmp_path / 'broken').mkdir()
    (tmp_path / 'broken' / 'metadata.yaml').write_text('rosbag2_bagfile_information: [')
    with pytest.raises(BagError, match='broken: cannot open the bag'):
        Bag(tmp_path / 'broken')


def test_a_storage_file_cut_short_says_how_to_repair_it(tmp_path, streams):
    """The error of rosbags, 'File end magic is invalid.', alone did not say what to do."""
    write_bag(tmp_path / 'cut', TOPICS, pose_messages(streams), 'mcap')
    (storage,) = (tmp_path / 'cut').glob('*.mcap')
    storage.write_bytes(storage.read_bytes()[:len(storage.read_bytes()) // 2])
    with pytest.raises(BagError, match='can be repaired with `mcap recover`'):
        Bag(tmp_path / 'cut')
    storage.write_bytes(b'\x00' * 8 + storage.read_bytes()[8:])   # no mcap at all: no advice
    with pytest.raises(BagError, match='cannot open the bag') as caught:
        Bag(tmp_path / 'cut')
    assert 'mcap recover' not in str(caught.value)
    write_bag(tmp_path / 'db', TOPICS, pose_messages(streams))
    (storage,) = (tmp_path / 'db').glob('*.db3')
    storage.write_bytes(storage.read_bytes()[:4096] + b'\x00' * 4096)
    with pytest.raises(BagError, match="repaired with sqlite3's `.recover`"):
        Bag(tmp_path / 'db')


def test_input_errors_name_the_topic(tmp_path, pose_bag):
    write_bag(tmp_path / 'empty', TOPICS, [])
    with Bag(tmp_path / 'empty') as recording:
        with pytest.raises(BagError, match='holds no messages'):
            Replay(recording, PoseInput('/link'), PoseInput('/sensor'))
    with Bag(pose_bag) as recording:
        with pytest.raises(BagError, match=r'no topic /nope \(link poses\).*\n  /link '
                                           r'\(geometry_msgs/msg/PoseStamped, \d+ messages\)'):
            Replay(recording, PoseInput('/nope'), PoseInput('/sensor'))
        with pytest.raises(BagError, match='both come from topic /link'):
            Replay(recording, PoseInput('/link'), PoseInput('/link'))
        with pytest.raises(BagError, match=r'no TF topic \(/tf, /tf_static\)'):
            Replay(recording, PoseInput(frames=('a', 'b')), PoseInput('/sensor'))
    string = TYPESTORE.types['std_msgs/msg/String']
    write_bag(tmp_path / 'chat', {'/chatter': 'std_msgs/msg/String', '/link': POSE_STAMPED,
                                  '/tf': bag.TF_TYPE},
              [('/chatter', 1, string(data='hi')), ('/tf', 2, tf_message([]))])
    with Bag(tmp_path / 'chat') as recording:
        with pytest.raises(BagError, match='topic /chatter .sensor poses. has type '
                                           'std_msgs/msg/String'):
            Replay(recording, PoseInput(frames=('a', 'b')), PoseInput('/chatter'))
        with pytest.raises(BagError, match=r'topic /link \(link poses\) has no messages'):
            Replay(recording, PoseInput('/link'), PoseInput(frames=('a', 'b')))
        with pytest.raises(BagError, match='holds tf2_msgs/TFMessage: give --sensor-frames'):
            Replay(recording, PoseInput(frames=('a', 'b')), PoseInput('/tf'))


def test_damaged_storage_is_a_bag_error(tmp_path, pose_bag, streams):
    path = tmp_path / 'b'
    write_bag(path, TOPICS, pose_messages(streams), 'mcap')
    data = next(path.glob('*.mcap'))
    data.write_bytes(data.read_bytes()[:len(data.read_bytes()) // 2])
    with pytest.raises(BagError, match=str(path)):
        with Bag(path) as recording:
            Replay(recording, PoseInput('/link'), PoseInput('/sensor')).run(Session())


def test_an_error_while_feeding_is_raised_as_it_is(pose_bag, monkeypatch):
    # The window of messages read ahead is fed again after damaged storage; after an error
    # while feeding it, that second feed failed on the half-fed window (an IndexError) and
    # hid the error itself.
    def failing(*args, **kwargs):
        raise RuntimeError('the error itself')
    monkeypatch.setattr(Session, 'add_poses', failing)
    monkeypatch.setattr(bag, 'WINDOW_BYTES', 0)   # fed as they are read
    with pytest.raises(RuntimeError, match='the error itself'):
        replay(pose_bag)


def awkward_bag(path, streams, link_type):
    """Both streams with bad, odd and late messages among the good ones; frame ids change."""
    messages = pose_messages(streams, link_type)
    links = [i for i, m in enumerate(messages) if m[0] == '/link']
    sensors = [i for i, m in enumerate(messages) if m[0] == '/sensor']
    link_pose = 'pose' if link_type == POSE_STAMPED else 'transform'
    position = 'position' if link_type == POSE_STAMPED else 'translation'
    getattr(getattr(messages[links[10]][2], link_pose), position).x = float('nan')
    getattr(getattr(messages[links[11]][2], link_pose), position).y = 1e308   # sum overflows
    getattr(getattr(messages[links[11]][2], link_pose), position).z = 1e308
    messages[links[30]][2].header.stamp.nanosec = 2_000_000_000
    messages[links[32]][2].header.stamp = messages[links[31]][2].header.stamp   # repeated
    messages[links[40]][2].header.frame_id = 'bäse'
    for i in links[200:300]:
        messages[i][2].header.frame_id = 'base_link'
    messages[sensors[3]][2].pose.position.y = float('inf')
    types = {'/link': link_type, '/sensor': POSE_STAMPED}
    with Writer(path, version=8) as writer:
        connections = {topic: writer.add_connection(topic, msgtype, typestore=TYPESTORE)
                       for topic, msgtype in types.items()}
        for k, (topic, log_ns, msg) in enumerate(messages):
            data = TYPESTORE.serialize_cdr(msg, types[topic], little_endian=k % 50 != 7)
            writer.write(connections[topic], log_ns, data)
            if k == links[60]:
                writer.write(connections[topic], log_ns, b'\x00\x01not a message')


def decoder_keeping(share, kept):
    """Return cdr.decode_poses that leaves all but `share` of its rows to rosbags."""
    rng = np.random.default_rng(8)

    def decode(raws, msgtype, **options):
        decoded = DECODE_POSES(raws, msgtype, **options)
        ok = decoded.ok & (rng.random(len(raws)) < share)
        kept.append(int(ok.sum()))
        return decoded._replace(ok=ok)
    return decode


# The one-message path sums the 1e308 coordinates (and numpy warns) to find them non-finite.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.parametrize('link_type, share', [(POSE_STAMPED, 1.0), (POSE_STAMPED, 0.7),
                                              (TRANSFORM_STAMPED, 1.0),
                                              (TRANSFORM_STAMPED, 0.7)])
def test_decoded_poses_give_what_one_message_at_a_time_gives(tmp_path, streams, monkeypatch,
                                                             link_type, share):
    """Rows decoded from the bytes, fed in runs, are the messages rosbags reads, fed singly."""
    awkward_bag(tmp_path / 'b', streams, link_type)
    kept = []
    monkeypatch.setattr(bag.cdr, 'decode_poses', decoder_keeping(share, kept))
    fast, fast_report = replay(tmp_path / 'b')
    assert sum(kept) > 0.9 * share * len(streams.link)
    monkeypatch.setattr(bag.cdr, 'decode_poses', decoder_keeping(0.0, []))
    slow, slow_report = replay(tmp_path / 'b')
    assert fast.counters == slow.counters and fast.counters['samples'] == 6
    for ours, theirs in zip(fast.samples, slow.samples, strict=True):
        assert ours.stamp_ns == theirs.stamp_ns
        for pose, other in ((ours.link, theirs.link), (ours.sensor, theirs.sensor)):
            assert np.array_equal(pose.position, other.position)
            assert np.array_equal(pose.quaternion, other.quaternion)
    assert fast_report.warnings() == slow_report.warnings()
    assert (fast_report.messages, fast_report.stamps, fast_report.frames) == \
        (slow_report.messages, slow_report.stamps, slow_report.frames)
    # A NaN link pose is refused by conversions, one of 1e308 coordinates by the position
    # bound (max_position_m); both are counted as bad messages.
    assert fast_report.bad == {
        ('link_pose', 'non_finite'): 1, ('link_pose', 'implausible_position'): 1,
        ('link_pose', 'bad_stamp'): 1,
        ('link_pose', 'undecodable'): 1, ('link_pose', 'duplicate_stamp'): 1,
        ('sensor_pose', 'non_finite'): 1}


@pytest.mark.parametrize('fast', [True, False])
def test_bags_get_the_message_checks_of_the_live_node(tmp_path, streams, monkeypatch, fast):
    """Zero stamps and header frames other than the configured one are counted and skipped."""
    messages = pose_messages(streams)
    links = [i for i, m in enumerate(messages) if m[0] == '/link']
    for i in links[40:44]:
        messages[i][2].header.stamp.sec = messages[i][2].header.stamp.nanosec = 0
    for i in links[50:53]:
        messages[i][2].header.frame_id = 'world'
    for i in links[60:62]:
        messages[i][2].header.frame_id = '/base'     # ROS 1 habit: the same frame
    write_bag(tmp_path / 'b', TOPICS, messages)
    if not fast:
        monkeypatch.setattr(bag.cdr, 'decode_poses', decoder_keeping(0.0, []))
    checks = CheckConfig(link_frame_id='base', sensor_frame_id='camera')
    session, report = replay(tmp_path / 'b', checks=checks)
    assert report.bad == {('link_pose', 'zero_stamp'): 4, ('link_pose', 'wrong_frame_id'): 3}
    assert any("/link: 3 message(s) skipped (wrong_frame_id): header.frame_id 'world' is not "
               "'base'" in w for w in report.warnings())
    assert session.counters['link_messages'] == len(streams.link) - 7
    _, report = replay(tmp_path / 'b', checks=CheckConfig(sensor_frame_id='cam'))
    assert report.bad == {('link_pose', 'zero_stamp'): 4,
                          ('sensor_pose', 'wrong_frame_id'): len(streams.sensor)}


def test_pose_with_covariance_topics_bring_their_covariances(tmp_path, streams, pose_bag):
    """A detector's PoseWithCovarianceStamped in a bag: the samples carry its covariance."""
    covariance = np.diag([1e-6, 1e-6, 9e-6, 3e-6, 3e-6, 1e-7])   # ROS order
    messages = [m for m in pose_messages(streams) if m[0] == '/link']
    messages += [('/sensor', delivered, conversions.pose_with_covariance_stamped_msg(
        Pose(pose.position, pose.quaternion, covariance), stamp, 'camera', typestore=TYPESTORE))
        for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    path = tmp_path / 'with_covariance'
    write_bag(path, {'/link': POSE_STAMPED,
                     '/sensor': 'geometry_msgs/msg/PoseWithCovarianceStamped'},
              sorted(messages, key=lambda m: m[1]))
    session, _ = replay(path)
    plain, _ = replay(pose_bag)
    assert len(session.samples) == len(plain.samples) >= 5
    for sample, other in zip(session.samples, plain.samples):
        np.testing.assert_allclose(sample.sensor.covariance, covariance, rtol=1e-12)
        np.testing.assert_allclose(sample.sensor.position, other.sensor.position, atol=1e-12)
