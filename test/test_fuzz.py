"""
Property-based fuzzing (hypothesis) of everything that takes outside data.

- The node's subscription callbacks (PoseStamped and TransformStamped), called directly on an
  in-process node with arbitrary floats (NaN, inf, huge), stamps (negative sec, nanosec out of
  range, zero, far from the clock) and frame ids.
- The node's parameter callback with arbitrary names and values.
- The samples CSV reader with arbitrary text and bytes, and `solve` on near-valid CSV files.
- The bag reader and the `replay` tool on corrupted rosbag2 recordings (sqlite3 and mcap).

The property: no exception escapes (except the documented error type), the node's counts
stay consistent (every message is counted once, as good or as bad under one reason), and good
data after bad still calibrates.  Examples are derandomised so that runs are repeatable; set
HYPOTHESIS_PROFILE=explore for more, random ones.  The nodes live on a domain id of conftest
(nothing is published).
"""

import contextlib
import io
import json
import os
import shutil
import tracemalloc

from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import TransformStamped
from hypothesis import given
from hypothesis import settings
from hypothesis import strategies as st
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.samples_csv import COLUMNS
from quatcal_ros.files.samples_csv import format_samples
from quatcal_ros.files.samples_csv import parse_samples
from quatcal_ros.files.samples_csv import read_samples
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.ros import conversions
from quatcal_ros.ros.bag import Bag
from quatcal_ros.ros.bag import BagError
from quatcal_ros.ros.bag import TYPESTORE
from quatcal_ros.ros.bag import write_bag
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
from quatcal_ros.stream import message_checks as mc
from quatcal_ros.stream import settings as table
from quatcal_ros.stream.session import STATES
from quatcal_ros.tools import cli
from rcl_interfaces.msg import SetParametersResult
import rclpy
from rclpy.context import Context
from rclpy.parameter import Parameter
from std_srvs.srv import Trigger

NS = NS_PER_S
MS = 1_000_000
FRAMES = {mc.LINK: 'base', mc.SENSOR: 'camera'}
# Parameters naming files the node writes: fuzzed through the check only (never set, so that
# no file is written at an arbitrary path).
FILE_PARAMETERS = [spec.name for spec in table.SETTINGS
                   if spec.name.endswith('_file') and spec.name != 'easy_handeye2_file']

SCALE = 10 if os.environ.get('HYPOTHESIS_PROFILE') == 'explore' else 1


def examples(n):
    """Return hypothesis settings for n test cases, ten times more when exploring."""
    return settings(max_examples=n * SCALE)


# --- strategies ------------------------------------------------------------------------------

any_float = st.floats(allow_nan=True, allow_infinity=True)
small_float = st.floats(-10.0, 10.0)


@st.composite
def quaternions_xyzw(draw):
    """Draw (x, y, z, w): a unit one (often), scaled slightly or far, zero, or any floats."""
    kind = draw(st.sampled_from(['unit', 'unit', 'unit', 'scaled', 'zero', 'any']))
    if kind == 'any':
        return tuple(draw(st.lists(any_float, min_size=4, max_size=4)))
    if kind == 'zero':
        return (0.0, 0.0, 0.0, 0.0)
    q = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4)))
    norm = np.linalg.norm(q)
    q = q / norm if norm > 1e-3 else np.array([0.0, 0.0, 0.0, 1.0])
    scale = 1.0 if kind == 'unit' else draw(st.one_of(
        st.floats(0.998, 1.002), st.floats(0.0, 1e6), st.sampled_from([-1.0, 1e-300, 1e300])))
    return tuple(float(v) for v in q * scale)


@st.composite
def stamps(draw, now_ns, index):
    """
    Draw (sec, nanosec) of the index-th message.

    Mostly a sequence near the node clock (10 ms apart, jittered so that some come out of
    order or repeat), else zero, far from the clock, or anything (negative sec, nanosec out
    of range).
    """
    kind = draw(st.sampled_from(['sequence'] * 5 + ['zero', 'far', 'any']))
    if kind == 'sequence':
        ns = now_ns - NS + index * 10 * MS + draw(st.sampled_from([0, 0, 0, -15 * MS, -10 * MS]))
    elif kind == 'zero':
        ns = 0
    elif kind == 'far':
        ns = now_ns + draw(st.integers(-40 * NS, 40 * NS))
    else:
        return draw(st.integers(-2 ** 31, 2 ** 31 - 1)), draw(st.integers(0, 2 ** 32 - 1))
    return divmod(ns, NS)


def frame_ids(stream):
    """Return a strategy of header frame ids for `stream`: mostly the expected one."""
    return st.one_of(st.just(FRAMES[stream]), st.just(FRAMES[stream]), st.just(FRAMES[stream]),
                     st.sampled_from(['base', 'camera', '', '/base', '/camera', 'world']),
                     st.text(max_size=12))


positions = st.lists(st.one_of(small_float, small_float, any_float), min_size=3, max_size=3)


@st.composite
def pose_messages(draw, now_ns, message_type, index=0):
    """Draw (stream, message) with arbitrary content, the index-th of a list."""
    stream = draw(st.sampled_from(mc.STREAMS))
    msg = message_type()
    msg.header.stamp.sec, msg.header.stamp.nanosec = draw(stamps(now_ns, index))
    msg.header.frame_id = draw(frame_ids(stream))
    if message_type is PoseStamped:
        position, orientation = msg.pose.position, msg.pose.orientation
    else:
        msg.child_frame_id = draw(st.text(max_size=8))
        position, orientation = msg.transform.translation, msg.transform.rotation
    position.x, position.y, position.z = draw(positions)
    orientation.x, orientation.y, orientation.z, orientation.w = draw(quaternions_xyzw())
    return stream, msg


@st.composite
def message_lists(draw, now_ns, message_type, min_size=0, max_size=40):
    """Draw a list of (stream, message), as pose_messages."""
    n = draw(st.integers(min_size, max_size))
    return [draw(pose_messages(now_ns, message_type, index)) for index in range(n)]


# --- the node's subscription callbacks -------------------------------------------------------

@pytest.fixture(scope='module')
def context(domain_id):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    yield context
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope='module')
def nodes(context, tmp_path_factory):
    """One calibrator per pose_type; frames are checked; files in a temporary directory."""
    files = tmp_path_factory.mktemp('fuzz_files')
    made = {}
    for pose_type, message_type in (('pose', PoseStamped), ('transform', TransformStamped)):
        overrides = [Parameter('pose_type', value=pose_type),
                     Parameter('link_frame_id', value=FRAMES[mc.LINK]),
                     Parameter('sensor_frame_id', value=FRAMES[mc.SENSOR]),
                     Parameter('still_window_s', value=0.3)]
        overrides += [Parameter(name, value=str(files / f'{pose_type}_{name}.txt'))
                      for name in FILE_PARAMETERS]
        node = CalibratorNode(context=context, namespace=f'/fuzz_{pose_type}',
                              parameter_overrides=overrides)
        node.get_logger().set_level(rclpy.logging.LoggingSeverity.ERROR)
        made[message_type] = node
    yield made
    for node in made.values():
        node.destroy_node()


def restart(node):
    """Start a fresh session and fresh counts on `node`."""
    node._on_reset(Trigger.Request(), Trigger.Response())
    node.inputs.screen.stats = mc.StreamStats()


def deliver(node, stream, msg):
    node.inputs._on_pose(stream, msg)


def assert_consistent(node, sent):
    """Each message was counted once; the session agrees; its state and numbers are sane."""
    stats = node.stats
    counters = node.session.counters
    for stream, key in ((mc.LINK, 'link_messages'), (mc.SENSOR, 'sensor_messages')):
        # A pose far behind its stream that the session holds until the next message says
        # whether it was stale is neither good nor bad yet.
        held = int(stream in node.session.held)
        assert stats.received[stream] == sent[stream]
        assert stats.received[stream] == stats.good[stream] + stats.bad_of(stream) + held
        # The session saw the good messages, those it refused itself and the one it holds.
        session_refused = sum(stats.bad[stream, reason] for reason in (
            'out_of_order', 'duplicate_stamp', 'stale_stamp'))
        assert counters[key] == stats.good[stream] + session_refused + held
    assert all(reason in mc.REASONS for _, reason in stats.bad)
    assert node.session.state in STATES
    for sample in node.session.samples:
        for pose in (sample.link, sample.sensor):
            assert np.all(np.isfinite(pose.position))
            assert abs(np.linalg.norm(pose.quaternion) - 1.0) < 1e-9
    result = node.session.result
    if result is not None:
        assert abs(np.linalg.norm(result.quaternion) - 1.0) < 1e-9
    status = node.diagnostic_status()
    values = {kv.key: kv.value for kv in status.values}
    assert values['bad_messages'] == str(stats.bad_total)
    node.publish_diagnostics()


def good_messages(node, message_type, seed, start_ns):
    """Return a noisy stop-and-go run (8 stops) as messages in delivery order, and its cell."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(
        rng, cell, n_stops=8, link_rate_hz=100.0, sensor_rate_hz=30.0, still_s=0.6,
        move_s=0.5, rotation_noise_deg=0.1, translation_noise_m=0.0005,
        rotation_spread_deg=40.0, start_ns=start_ns)

    def build(pose, stamp, stream):
        if message_type is PoseStamped:
            return conversions.pose_stamped_msg(pose, stamp, FRAMES[stream])
        return conversions.transform_stamped_msg(pose, stamp, FRAMES[stream], 'child')

    events = [(stamp, 0, mc.LINK, build(pose, stamp, mc.LINK)) for stamp, pose in streams.link]
    events += [(delivered, 1, mc.SENSOR, build(pose, stamp, mc.SENSOR))
               for delivered, (stamp, pose) in zip(streams.sensor_delivery_ns, streams.sensor)]
    events.sort(key=lambda e: e[:2])
    return cell, [(stream, msg) for _, _, stream, msg in events]


# Positions of 1e308 m are finite, so accepted; the still check's norms overflow on them.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.parametrize('message_type', [PoseStamped, TransformStamped])
def test_callbacks_never_raise_and_count_every_message(nodes, message_type):
    node = nodes[message_type]
    now_ns = node.now_ns()

    @examples(100)
    @given(message_lists(now_ns, message_type))
    def run(messages):
        restart(node)
        sent = dict.fromkeys(mc.STREAMS, 0)
        for stream, msg in messages:
            deliver(node, stream, msg)
            sent[stream] += 1
        assert_consistent(node, sent)

    run()


# Positions of 1e308 m are finite, so accepted; the still check's norms overflow on them.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.parametrize('message_type', [PoseStamped, TransformStamped])
def test_good_data_after_bad_still_calibrates(nodes, message_type):
    node = nodes[message_type]
    now_ns = node.now_ns()

    @examples(6)
    @given(message_lists(now_ns, message_type, min_size=20, max_size=60),
           st.integers(0, 2 ** 16))
    def run(messages, seed):
        restart(node)
        sent = dict.fromkeys(mc.STREAMS, 0)
        for stream, msg in messages:
            deliver(node, stream, msg)
            sent[stream] += 1
        cell, good = good_messages(node, message_type, seed, node.now_ns() - 15 * NS)
        for stream, msg in good:
            deliver(node, stream, msg)
            sent[stream] += 1
        assert_consistent(node, sent)
        result = node.session.result
        assert result is not None, node.session.last_error
        error = np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))
        assert error < 3.0 * result.uncertainty_deg + 0.05, (error, result.uncertainty_deg)

    run()


# --- the parameter callback ------------------------------------------------------------------

PARAMETER_NAMES = [spec.name for spec in table.SETTINGS]
parameter_values = st.one_of(
    st.none(), st.booleans(), st.integers(-2 ** 63, 2 ** 63 - 1), any_float,
    st.text(max_size=20), st.sampled_from(['pose', 'transform', 'eye_to_hand', 'manual',
                                           'continuous', 'consecutive', 'all', '']),
    st.lists(st.integers(-2 ** 63, 2 ** 63 - 1), max_size=3),
    st.lists(any_float, max_size=3), st.lists(st.text(max_size=5), max_size=3),
    st.lists(st.booleans(), max_size=3), st.lists(st.binary(min_size=1, max_size=1), max_size=3))
parameters = st.builds(
    lambda name, value: Parameter(name, value=value),
    st.one_of(st.sampled_from(PARAMETER_NAMES), st.text(min_size=1, max_size=10)),
    parameter_values)


def _parameter_value(parameter):
    return parameter.value


def test_parameter_callback_never_raises(nodes):
    node = nodes[PoseStamped]
    defaults = [Parameter(spec.name, value=spec.default) for spec in table.SETTINGS
                if not spec.read_only and not spec.name.endswith('_file')]

    @examples(300)
    @given(st.lists(parameters, min_size=1, max_size=4))
    def run(batch):
        result = node._check_parameters(batch)
        assert isinstance(result, SetParametersResult)
        if not result.successful:
            assert result.reason
        # The whole path: rclpy's own checks (types, ranges, read-only), then ours, then
        # the post-set callback that rebuilds the session.
        declared = [p for p in batch
                    if node.has_parameter(p.name) and not p.name.endswith('_file')]
        for outcome in node.set_parameters(declared):
            assert outcome.successful or outcome.reason
        assert node.config == table.Settings.from_values(
            {name: node.get_parameter(name).value for name in PARAMETER_NAMES})

    try:
        run()
    finally:
        assert all(r.successful for r in node.set_parameters(defaults))
    # Good data still calibrates with the parameters back at their defaults.
    restart(node)
    node.set_parameters([Parameter('still_window_s', value=0.3)])
    cell, good = good_messages(node, PoseStamped, 3, node.now_ns() - 15 * NS)
    for stream, msg in good:
        deliver(node, stream, msg)
    result = node.session.result
    assert result is not None, node.session.last_error
    error = np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))
    assert error < 3.0 * result.uncertainty_deg + 0.05


# --- the samples CSV reader ------------------------------------------------------------------

cells = st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr),
                  st.floats(-2.0, 2.0).map(repr), st.integers().map(str),
                  st.sampled_from(['', ' ', 'nan', '-inf', '1e400', '0x10', '1_0', '"1"', '#']),
                  st.text(max_size=8))


@st.composite
def near_csv(draw):
    """Draw a header (columns shuffled, some missing or extra) and rows of any cells."""
    columns = list(COLUMNS)
    if draw(st.booleans()):
        columns = draw(st.permutations(columns))
    if draw(st.booleans()):
        columns = columns[:draw(st.integers(0, len(columns)))] + draw(
            st.lists(st.text(max_size=6), max_size=2))
    rows = draw(st.lists(st.lists(cells, min_size=0, max_size=len(columns) + 1), max_size=6))
    lines = [','.join(columns)] + [','.join(row) for row in rows]
    return draw(st.sampled_from(['\n', '\r\n', '\r'])).join(lines)


@examples(400)
@given(st.one_of(st.text(), near_csv()))
def test_samples_csv_reader_raises_only_bad_input_error(text):
    try:
        samples = parse_samples(text, 'fuzz.csv')
    except BadInputError as error:
        assert str(error).startswith('fuzz.csv')
        return
    for sample in samples:
        for pose in (sample.link, sample.sensor):
            assert np.all(np.isfinite(pose.position))
            assert abs(np.linalg.norm(pose.quaternion) - 1.0) < 1e-9


@examples(100)
@given(st.binary(max_size=300))
def test_samples_csv_file_of_random_bytes(tmp_path_factory, data):
    path = tmp_path_factory.mktemp('csv') / 'samples.csv'
    path.write_bytes(data)
    try:
        read_samples(path)
    except BadInputError as error:
        assert str(path) in str(error)


@st.composite
def sample_rows(draw):
    """Draw valid samples CSV text: unit quaternions, positions and stamps in range."""
    n = draw(st.integers(0, 8))
    rows = [','.join(COLUMNS)]
    for k in range(n):
        values = [draw(st.one_of(st.floats(-1e9, 1e9), st.just(float(k))))]
        for _ in range(2):
            values += draw(st.lists(st.one_of(st.floats(-1e300, 1e300), small_float),
                                    min_size=3, max_size=3))
            q = np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4)))
            norm = np.linalg.norm(q)
            values += list(q / norm) if norm > 1e-3 else [0.0, 0.0, 0.0, 1.0]
        rows.append(','.join(repr(float(v)) for v in values))
    return '\n'.join(rows) + '\n'


def _no_constant(name):
    raise AssertionError(f'the JSON output holds {name}, which strict JSON readers refuse')


# Positions of 1e300 m are valid numbers, and overflow in the translation's sums.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.filterwarnings('ignore:invalid value encountered:RuntimeWarning')
@examples(60)
@given(st.one_of(sample_rows(), near_csv()))
def test_solve_exits_0_2_or_3(tmp_path_factory, text):
    path = tmp_path_factory.mktemp('solve') / 'samples.csv'
    path.write_text(text)
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = cli.solve_main([str(path)])
    assert status in (0, 2, 3), err.getvalue()
    if status:
        assert 'solve: error:' in err.getvalue()
    else:
        json.loads(out.getvalue(), parse_constant=_no_constant)


def test_solve_of_good_samples_after_fuzzing(tmp_path):
    rng = np.random.default_rng(12)
    cell = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, cell, 12, rotation_noise_deg=0.1)
    path = tmp_path / 'samples.csv'
    path.write_text(format_samples(samples))
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert cli.solve_main([str(path)]) == 0


# --- the bag reader and the replay tool ------------------------------------------------------

@pytest.fixture(scope='module')
def bags(tmp_path_factory):
    """Write a small good recording in each storage format: {storage: bag directory}."""
    rng = np.random.default_rng(31)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(
        rng, cell, 5, link_rate_hz=100.0, sensor_rate_hz=30.0, still_s=0.6, move_s=0.5,
        rotation_noise_deg=0.1, rotation_spread_deg=40.0)
    kind = 'geometry_msgs/msg/PoseStamped'
    messages = [('/link', stamp, conversions.pose_stamped_msg(pose, stamp, 'base',
                                                              typestore=TYPESTORE))
                for stamp, pose in streams.link]
    messages += [('/sensor', delivered, conversions.pose_stamped_msg(pose, stamp, 'camera',
                                                                     typestore=TYPESTORE))
                 for delivered, (stamp, pose) in zip(streams.sensor_delivery_ns,
                                                     streams.sensor)]
    messages.sort(key=lambda m: m[1])
    out = {}
    for storage in ('sqlite3', 'mcap'):
        path = tmp_path_factory.mktemp('bags') / storage
        write_bag(path, {'/link': kind, '/sensor': kind}, messages, storage=storage)
        out[storage] = path
    return out


def replay(path):
    """Run the replay tool in-process; return (exit status, stderr)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = cli.replay_main([str(path), '--link-topic', '/link', '--sensor-topic',
                                  '/sensor', '--quiet'])
    return status, err.getvalue()


def test_the_good_bags_replay(bags):
    for path in bags.values():
        assert replay(path) == (0, '')


@st.composite
def corruptions(draw):
    """Draw a list of (what, where as a fraction of the file, bytes) to apply to a bag."""
    return draw(st.lists(st.tuples(
        st.sampled_from(['flip', 'flip', 'truncate', 'metadata', 'garbage']),
        st.floats(0.0, 1.0), st.binary(min_size=1, max_size=16)), min_size=1, max_size=4))


def corrupt(source, target, changes):
    shutil.copytree(source, target)
    storage = next(p for p in target.iterdir() if p.suffix in ('.db3', '.mcap'))
    for what, where, data in changes:
        if what == 'metadata':
            metadata = target / 'metadata.yaml'
            text = metadata.read_bytes()
            at = int(where * len(text))
            metadata.write_bytes(text[:at] + data + text[at + len(data):])
            continue
        content = bytearray(storage.read_bytes())
        at = min(int(where * len(content)), max(len(content) - 1, 0))
        if what == 'flip':
            content[at:at + len(data)] = bytes(
                a ^ b for a, b in zip(content[at:at + len(data)], data))
        elif what == 'truncate':
            del content[at:]
        else:
            content = bytearray(data * 64)
        storage.write_bytes(bytes(content))


# Flipped bytes make huge (finite) coordinates, which overflow in the estimator's sums.
@pytest.mark.filterwarnings('ignore:overflow encountered:RuntimeWarning')
@pytest.mark.filterwarnings('ignore:invalid value encountered:RuntimeWarning')
@pytest.mark.parametrize('storage', ['sqlite3', 'mcap'])
def test_replay_of_corrupted_bags_exits_cleanly(bags, storage, tmp_path_factory):

    @examples(25)
    @given(corruptions())
    def run(changes):
        path = tmp_path_factory.mktemp('corrupt') / 'bag'
        corrupt(bags[storage], path, changes)
        try:
            with Bag(path) as recording:
                recording.describe_topics()
        except BagError as error:
            assert str(path) in str(error)
        status, err = replay(path)
        assert status in (0, 2, 3), err
        if status:
            assert err.startswith('replay: error:'), err
            assert 'Traceback' not in err
        shutil.rmtree(path)

    run()


@examples(40)
@given(st.binary(max_size=2000), st.sampled_from(['samples.db3', 'x.mcap', 'metadata.yaml']))
def test_random_files_are_not_bags(tmp_path_factory, data, name):
    directory = tmp_path_factory.mktemp('random')
    path = directory / name
    path.write_bytes(data)
    target = directory if name == 'metadata.yaml' else path
    with pytest.raises(BagError):
        with Bag(target):
            pass
    status, err = replay(target)
    assert status == 2 and err.startswith('replay: error:'), err


# --- the bounded YAML and JSON loader --------------------------------------------------------

@st.composite
def hostile_yaml(draw):
    """YAML that anchors and aliases, nests, and writes long integers, at random."""
    fan = draw(st.integers(1, 12))
    levels = draw(st.integers(0, 12))
    lines = ['l0: &l0 [' + ', '.join(['x'] * fan) + ']']
    lines += [f'l{k}: &l{k} [' + ', '.join([f'*l{k - 1}'] * fan) + ']'
              for k in range(1, levels + 1)]
    depth = draw(st.integers(0, 300))
    lines.append('deep: ' + '[' * depth + ']' * depth)
    lines.append('n: ' + '9' * draw(st.integers(1, 6000)))
    lines += draw(st.lists(st.text(max_size=30), max_size=3))
    return '\n'.join(draw(st.permutations(lines)))


def _bounded_load(load, text):
    """Load `text`; return the peak memory (bytes) it took, refused or not."""
    tracemalloc.start()
    try:
        load(text, 'fuzz.yaml')
    except BadInputError as error:
        assert str(error).startswith('fuzz.yaml')
    finally:
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
    return peak


@examples(150)
@given(st.one_of(hostile_yaml(), st.text(max_size=200)))
def test_the_yaml_loader_refuses_or_loads_in_bounded_memory(text):
    # No alias expands, nothing nests past 64 levels: a few MB at most, whatever the text.
    assert _bounded_load(plain_yaml.load, text) < 64 * 1024 * 1024


@examples(150)
@given(st.one_of(st.integers(0, 5000).map(lambda n: '[' * n + ']' * n),
                 st.integers(1, 6000).map(lambda n: '[' + '7' * n + ']'),
                 st.text(max_size=200)))
def test_the_json_loader_refuses_or_loads_in_bounded_memory(text):
    assert _bounded_load(plain_yaml.load_json, text) < 64 * 1024 * 1024
