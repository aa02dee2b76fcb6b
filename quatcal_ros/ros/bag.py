"""
Replay a rosbag2 recording (sqlite3 or mcap) into a session.Session, as the live node would.

Read with the pure-Python `rosbags` library (types of ROS 2 Jazzy), in the bag's order (log
time); poses always carry their header stamps.  A pose stream (`PoseInput`) comes from a
topic of geometry_msgs/PoseStamped, TransformStamped, PoseWithCovarianceStamped or
nav_msgs/Odometry, or from two frames of the transform tree of tf2_msgs/TFMessage topics
(/tf, /tf_static): T_target_source at each stamp at which a dynamic transform on the chain
arrived (tf_tree.FramePoses).  Static transforms are read first, wherever they are in the bag;
a static transform sent again with a new value holds from where it is in the bag on.
The sensor poses can also come from camera images (sensor_msgs Image or CompressedImage) with
their CameraInfo topic: the board's pose in each, found as the live node finds it
(image_input.ImageInput), and each still sample's corners kept by the ImageSensor.

Messages are read ahead a window at a time.  PoseStamped and TransformStamped topics take a
fast path: the window's messages of such a topic are decoded together straight from the raw
bytes (cdr.py), and each run of consecutive messages of the topic goes to the session at once
(Session.add_poses).  What that decoder does not vouch for, and every other type, is
deserialised by rosbags and handed over one message at a time.  Both give the same poses in
the bag's order, so the session sees exactly what it would see message by message.

Bad input raises BagError naming the file or topic.  A message that cannot be used (NaN,
zero quaternion, undecodable bytes) is counted and skipped; `ReplayReport.warnings()` says
how many, where and why.
"""

from collections import Counter
from dataclasses import dataclass, field
from itertools import groupby
from pathlib import Path

from quatcal_ros.files import bag_folder
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.ros import cdr
from quatcal_ros.ros.conversions import frame_ids
from quatcal_ros.ros.image_input import ImageInput
from quatcal_ros.ros.pose_screen import PoseScreen
from quatcal_ros.ros.tf_feed import DEFAULT_TF_TOPICS, is_static_tf_topic, kept_swapped, \
    TF_MAX_GAP_NS, TfFeed
from quatcal_ros.stream import frame_notices
from quatcal_ros.stream.message_checks import CheckConfig, LINK, SENSOR
from quatcal_ros.stream.tf_tree import normalize_frame
from rosbags.rosbag2 import Reader, StoragePlugin, Writer
from rosbags.typesys import get_typestore, Stores

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
IMAGE_TYPES = ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage')
CAMERA_INFO_TYPE = 'sensor_msgs/msg/CameraInfo'
POSE_TYPES = ('geometry_msgs/msg/PoseStamped', 'geometry_msgs/msg/TransformStamped',
              'geometry_msgs/msg/PoseWithCovarianceStamped', 'nav_msgs/msg/Odometry')
TF_TYPE = 'tf2_msgs/msg/TFMessage'
# Messages are read ahead (and the progress callback runs) this many at a time.
PROGRESS_EVERY = 512
# ... or fewer when they hold this many bytes: 512 raw 1080p images held 3 GB.
WINDOW_BYTES = 32 * 1024 * 1024
STORAGES = {'sqlite3': StoragePlugin.SQLITE3, 'mcap': StoragePlugin.MCAP}


class BagError(ValueError):
    """A recording or topic that cannot be replayed; the message names the file or topic."""


# --- the recording ---------------------------------------------------------------------------

class DamagedStorage(BagError):
    """Storage that cannot be read on, or not trusted (replay --partial uses what was read)."""


class Bag:
    """An open rosbag2 recording: its topics, and raw messages in log-time order."""

    def __init__(self, path):
        self.path = Path(path)
        self._reader = _open_reader(self.path)
        try:
            self.topics = {name: (info.msgtype, info.msgcount)
                           for name, info in self._reader.topics.items()}
            self.message_count = self._reader.message_count
        except Exception as error:   # noqa: B902 - whatever a damaged bag raises
            self.close()
            raise BagError(f"{self.path}: cannot read the bag's index: {error}") from None

    def close(self):
        """Close the files."""
        if self._reader.is_open:
            self._reader.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc_info):
        self.close()
        return False

    def describe_topics(self):
        """List the topics as 'name (type, N messages)', one per line, for messages."""
        if not self.topics:
            return '  (none)'
        return '\n'.join(f'  {name} ({msgtype or "several types"}, {count} messages)'
                         for name, (msgtype, count) in sorted(self.topics.items()))

    def topic_type(self, topic, allowed, role):
        """Return the message type of `topic`; BagError when missing, empty or not allowed."""
        if topic not in self.topics:
            raise BagError(f'{self.path}: no topic {topic} ({role}) in the bag; its topics:\n'
                           f'{self.describe_topics()}')
        msgtype, count = self.topics[topic]
        if msgtype not in allowed:
            raise BagError(f'{self.path}: topic {topic} ({role}) has type '
                           f'{msgtype or "(several types)"}, which the replay cannot read as '
                           f'{role}; supported: {", ".join(allowed)}')
        if count == 0:
            raise BagError(f'{self.path}: topic {topic} ({role}) has no messages')
        return msgtype

    def connections(self, topics):
        """Return the connections of `topics`."""
        return [c for c in self._reader.connections if c.topic in topics]

    def messages(self, connections):
        """Yield (connection, log time ns, raw bytes); BagError when the storage is damaged."""
        if not connections:
            return   # rosbags reads every topic when given none
        read = 0
        try:
            for connection, log_ns, raw in self._reader.messages(connections):
                read += 1
                if not isinstance(raw, (bytes, bytearray, memoryview)):   # a number in a db3
                    raw = b''   # (counted as undecodable, as text there is)
                yield connection, log_ns, raw
        except Exception as error:   # noqa: B902 - sqlite, mcap and zstd errors alike
            raise DamagedStorage(f'{self.path}: the recording is damaged after {read} '
                                 f'messages: {type(error).__name__}: {error}') from None

    def cut_short(self, read):
        """Raise DamagedStorage for storage cut inside a page (_cut_short), `read` read."""
        cut = _cut_short(self.path)
        if cut:   # sqlite read the torn page without a word
            raise DamagedStorage(f'{self.path}: the recording is damaged after {read} '
                                 f'messages: {cut}')


def _cut_short(path):
    """
    Say which sqlite storage file of the bag at `path` ends inside a page, or return ''.

    A db3 cut short by a few bytes still opens and reads, its last page filled up with
    zeros: a pose of the last messages came out 3.9 deg off, and was used. Its size is then
    no multiple of its page size (the header's bytes 16-17; 1 means 65536).
    """
    if path.suffix == '.db3':
        files = [path]
    else:   # those the index lists (a half-copied file beside them is none of the bag's)
        try:
            index = (path / bag_folder.INDEX).read_text(errors='replace')
        except OSError:
            index = None
        files = [file for file in bag_folder.storage_files(path, ('.db3',))
                 if index is None or file.name in index]
    for file in files:
        try:
            with open(file, 'rb') as stream:
                header = stream.read(18)
            size = file.stat().st_size
        except OSError:
            continue
        if len(header) < 18 or not header.startswith(b'SQLite format 3\0'):
            continue
        page = int.from_bytes(header[16:18], 'big')
        page = 65536 if page == 1 else page
        if page and size % page:
            return (f'{file.name} ends inside a page ({size} bytes, pages of {page}): it was '
                    'cut short, and its last messages may be corrupt')
    return ''


def _open_reader(path):
    if not path.exists():
        raise BagError(f'{path}: no such file or directory')
    if path.is_dir() and not (path / bag_folder.INDEX).is_file():
        parts = bag_folder.storage_files(path, bag_folder.READABLE_SUFFIXES)
        if not parts:   # nothing recorded here: no index to rebuild
            held = sorted(p.name for p in path.iterdir())
            listed = (f'; it holds {", ".join(held[:5])}{", ..." if len(held) > 5 else ""}'
                      if held else '; it is empty')
            raise BagError(f'{path}: not a rosbag2 directory: no {bag_folder.INDEX} and no '
                           f'{" or ".join(bag_folder.READABLE_SUFFIXES)} file in it{listed}')
        alone = f'; its storage file replays without it: {parts[0]}' if len(parts) == 1 else ''
        raise BagError(f'{path}: not a rosbag2 directory (no {bag_folder.INDEX} in it); if the '
                       f'recorder was killed, `ros2 bag reindex` can rebuild it{alone}')
    if path.is_file() and path.suffix not in bag_folder.READABLE_SUFFIXES:
        raise BagError(f'{path}: not a rosbag2 directory (nor a .db3 or .mcap file)')
    if path.is_file() and (path.parent / bag_folder.INDEX).is_file():
        parts = [p.name for p in bag_folder.storage_files(path.parent, (path.suffix,))]
        if len(parts) > 1:   # a split recording: this file alone is part of it
            raise BagError(f'{path}: one of the {len(parts)} storage files of the bag in '
                           f'{path.parent} ({", ".join(parts)}): give the folder, '
                           f'{path.parent}, to replay all of it')
    try:
        reader = Reader(path)
        reader.open()
    except Exception as error:   # noqa: B902 - rosbags, yaml, sqlite and mcap errors alike
        raise BagError(f'{path}: cannot open the bag: {str(error).rstrip(".")}'
                       f'{_repair_hint(error)}') from None
    return reader


def _repair_hint(error):
    """Return how to repair a storage file cut short (a crash, a full disk), or ''."""
    text = str(error)
    if 'end magic' in text.lower():   # mcap without its end (rosbags: 'File end magic ...')
        return ('; an mcap file cut short (the recorder killed, a full disk) can be repaired '
                'with `mcap recover` (the mcap CLI), then replayed')
    if 'malformed' in text or 'not a database' in text:   # sqlite3
        return ("; a .db3 file cut short can often be repaired with sqlite3's `.recover`, "
                'then `ros2 bag reindex`')
    return ''


def write_bag(path, topics, messages, storage='sqlite3'):
    """
    Write a rosbag2 directory (tests, benchmarks, dataset conversion).

    topics: {name: message type}; messages: iterable of (topic, log time ns, message built
    with TYPESTORE's classes); storage: 'sqlite3' or 'mcap'.  Returns the number written.
    """
    count = 0
    with Writer(Path(path), version=8, storage_plugin=STORAGES[storage]) as writer:
        connections = {name: writer.add_connection(name, msgtype, typestore=TYPESTORE)
                       for name, msgtype in topics.items()}
        for topic, log_ns, msg in messages:
            connection = connections[topic]
            writer.write(connection, int(log_ns),
                         TYPESTORE.serialize_cdr(msg, connection.msgtype))
            count += 1
    return count


# --- what to replay --------------------------------------------------------------------------

@dataclass(frozen=True)
class PoseInput:
    """Where a pose stream comes from: a pose `topic`, or `frames` (target, source) of TF."""

    topic: str = None
    frames: tuple = None
    # With camera_info set, `topic` holds camera images (sensor_msgs Image or
    # CompressedImage): the sensor poses are the board's, found by an ImageSensor.
    camera_info: str = None

    def __post_init__(self):
        if (self.topic is None) == (self.frames is None):
            raise ValueError('a pose input is a topic or a pair of frames, not both or none')
        if self.camera_info is not None and self.topic is None:
            raise ValueError('images come from a topic, not from TF frames')
        if self.frames is not None:   # as the transforms name them: '/tool0' is tool0
            object.__setattr__(self, 'frames', tuple(map(normalize_frame, self.frames)))
            if self.frames[0] == self.frames[1]:
                raise BadInputError(f'the frames {self.frames[0]} -> {self.frames[1]} are one '
                                    'frame: its pose never moves')

    def __str__(self):
        if self.camera_info is not None:
            return f'{self.topic} (images, with {self.camera_info})'
        if self.topic is not None:
            return self.topic
        return f'TF {self.frames[0]} -> {self.frames[1]}'


@dataclass
class ReplayReport:
    """
    What a replay read and what it could not use.

    `bad` counts the messages skipped as the live node counts them (pose_screen.PoseScreen,
    message_checks.REASONS), by (where, reason): `where` is a pose stream (link_pose,
    sensor_pose) or a TF topic, whose items are transforms; `examples` holds the first
    explanation of each; `sources` names each stream's topic or frames.
    """

    messages: int = 0
    stamps: dict = field(default_factory=dict)             # stream: [first, last] pose stamp
    logged: dict = field(default_factory=dict)             # topic: [first, last] log time
    frames: dict = field(default_factory=dict)             # stream: (frame_id, child frame)
    bad: Counter = field(default_factory=Counter)          # (where, reason): count
    good: Counter = field(default_factory=Counter)         # checked stream: poses used
    examples: dict = field(default_factory=dict)           # (where, reason): first text
    sources: dict = field(default_factory=dict)            # stream: topic or TF frames
    tf_dropped: dict = field(default_factory=dict)         # stream: its tf_tree.FramePoses
    unread: dict = field(default_factory=dict)             # topic: (read, indexed) when fewer
    damaged: str = ''                                      # why reading stopped (partial)
    tf_stale: int = 0   # transforms older than the TF buffer (also counted as out_of_order)
    tf_frames: tuple = ()                                  # every frame the TF tree knew
    tf_swapped: list = field(default_factory=list)   # TfFeed.swapped_frames' warnings
    tree: object = None   # the TF tree at the end (the result's joint in it, tf_joint)
    static_tf_topics: tuple = ()                           # those read, e.g. /tf_static
    static_tf_unread: tuple = ()                           # the bag's others, not asked for
    counters: dict = field(default_factory=dict)           # the session's, at the end
    camera_changes: list = field(default_factory=list)   # ImageSensor.set_camera's sentences

    def unread_text(self):
        """Say which topics' indexed messages could not all be read, or ''."""
        return '; '.join(f'{topic}: {read} of the {indexed} messages its index lists'
                         + (' (none: does metadata.yaml give the topic the type its messages '
                            'have?)' if not (read or self.damaged) else '')
                         for topic, (read, indexed) in self.unread.items())

    def warnings(self, said=()):
        """
        Return what was not used, as sentences for the JSON "warnings".

        said: streams whose TF stamps not evaluated the caller has named already.
        """
        out = []
        if self.unread or self.damaged:   # (a db3 cut inside its last page: all were read)
            out.append('partial replay: the recording is damaged'
                       + (f', read only {self.unread_text()}' if self.unread else '')
                       + (f' ({self.damaged})' if self.damaged else ''))
        for key, count in sorted(self.bad.items()):
            where, reason = key
            item = 'message' if where in self.sources else 'transform'
            out.append(f'{self.sources.get(where, where)}: {count} {item}(s) skipped '
                       f'({reason}): {self.examples[key]}')
        for stream, frames in sorted(self.tf_dropped.items()):
            if sum(frames.dropped.values()) and stream not in said:
                reasons = ', '.join(f'{n} {why}' for why, n in sorted(frames.dropped.items()))
                out.append(f'{stream} pose {frames.target} -> {frames.source}: stamps not '
                           f'evaluated ({reasons}); last: {frames.last_dropped}')
        jumps = self.counters.get('time_jumps', 0)
        if jumps:
            out.append(f'time jumped back {jumps} time(s) (a bag played twice?): pairing '
                       'restarted each time')
        repeated = self.counters.get('repeated_samples', 0)
        if repeated:
            out.append(f'{repeated} still sample(s) repeat earlier ones (the same data played '
                       'again) and were not added')
        unpaired = self.counters.get('unpaired', 0)
        if unpaired:
            out.append(f'{unpaired} pose stamp(s) of the slower stream could not be paired '
                       '(gaps in the faster stream, or stamps outside its range)')
        changes = self.camera_changes
        if changes:   # (the views dropped with them had gone without a word)
            out.append(changes[0] if len(changes) == 1 else
                       f'camera_info changed {len(changes)} times; the first: {changes[0]}; '
                       f'the last: {changes[-1]}')
        return out


class Replay:
    """
    Feeds one recording into a session: link and sensor poses in the bag's order.

    Inputs are checked against the bag when built (BagError); `run(session)` can be called
    more than once (for instance again in another capture mode).
    """

    def __init__(self, bag, link, sensor, tf_topics=DEFAULT_TF_TOPICS,
                 tf_max_gap_ns=TF_MAX_GAP_NS, checks=CheckConfig(), images=None):
        """
        Check the inputs against the bag (BagError).

        :param images: the vision.image_sensor.ImageSensor that finds the board when the
            sensor input is an image topic (PoseInput.camera_info set).
        """
        self.bag = bag
        self.inputs = {'link': link, 'sensor': sensor}
        self.checks = checks   # message_checks.CheckConfig, as the live node checks
        self.tf_max_gap_ns = tf_max_gap_ns
        self.images = images
        if bag.message_count == 0:
            raise BagError(f'{bag.path}: the bag holds no messages')
        if link.topic is not None and link.topic == sensor.topic:
            raise BagError(f'{bag.path}: the link and sensor poses cannot both come from topic '
                           f'{link.topic}')
        self.msgtypes = {}
        for stream, source in self.inputs.items():
            if source.camera_info is not None:
                self._check_image_topics(source)
            elif source.topic is not None:
                self.msgtypes[source.topic] = self._pose_topic_type(stream, source.topic)
        self.tf_topics = ()
        if any(source.frames for source in self.inputs.values()):
            self.tf_topics = tuple(t for t in tf_topics if t in bag.topics)
            self._check_tf_topics(tf_topics)
        self.topics = set(self.msgtypes) | set(self.tf_topics)
        self.total = sum(bag.topics[topic][1] for topic in self.topics)

    def _check_image_topics(self, source):
        if self.images is None:
            raise BagError('an image topic needs the board file (--board-file)')
        self.msgtypes[source.topic] = self.bag.topic_type(source.topic, IMAGE_TYPES,
                                                          'camera images')
        self.msgtypes[source.camera_info] = self.bag.topic_type(
            source.camera_info, (CAMERA_INFO_TYPE,),
            'camera calibration; another topic: --camera-info-topic')

    def _pose_topic_type(self, stream, topic):
        role = f'{stream} poses'
        if self.bag.topics.get(topic, (None,))[0] == TF_TYPE:
            raise BagError(f'{self.bag.path}: topic {topic} ({role}) holds tf2_msgs/TFMessage: '
                           f'give --{stream}-frames PARENT CHILD instead of --{stream}-topic')
        return self.bag.topic_type(topic, POSE_TYPES, role)

    def _check_tf_topics(self, wanted):
        if not self.tf_topics:
            raise BagError(f'{self.bag.path}: no TF topic ({", ".join(wanted)}) in the bag; '
                           f'its topics:\n{self.bag.describe_topics()}')
        for topic in self.tf_topics:
            msgtype = self.bag.topics[topic][0]
            if msgtype != TF_TYPE:
                raise BagError(f'{self.bag.path}: topic {topic} has type {msgtype}, not '
                               f'{TF_TYPE}')

    def run(self, session, on_progress=None, partial=False):
        """
        Replay the whole bag into `session`; return a ReplayReport.

        on_progress(messages read) is called every PROGRESS_EVERY messages.  The messages read
        of each topic are counted against the bag's index (ReplayReport.unread: a damaged
        storage can lose messages silently).  Storage that cannot be read on raises BagError,
        unless `partial`: then what was read is used and ReplayReport.damaged says why it
        stopped.
        """
        read = Counter()   # messages read per topic, against the bag's index
        run = _Run(self, session)
        try:
            count = self._read(run, read, on_progress)
            self.bag.cut_short(count)   # (after the last pass: the static one reads first)
        except BagError as error:
            if not partial:
                raise
            run.report.damaged = str(error)
            count = sum(read.values())
        report = run.finish(count)
        indexed = {topic: self.bag.topics[topic][1] for topic in self.topics}
        report.unread = {topic: (read[topic], indexed[topic]) for topic in sorted(self.topics)
                         if read[topic] < indexed[topic]}
        return report

    def _read(self, run, read, on_progress):
        """
        Feed the bag's messages to `run`; return their count.

        Static transforms first, wherever they are in the bag (a recorder that subscribed
        late still gets them): each edge's first value holds from the start, and a later
        value from where it is in the bag on, as a live tf2 listener would apply it.
        """
        static = {topic for topic in self.tf_topics if is_static_tf_topic(topic)}
        count, later = 0, []   # later: (log time, _StaticFeed) of each static message
        for connection, log_ns, raw in self.bag.messages(self.bag.connections(static)):
            count += 1
            read[connection.topic] += 1
            transforms = run.on_tf(connection.topic, raw, static=True, keep=True)
            if transforms:
                later.append((log_ns, _StaticFeed(run.tf, connection.topic, transforms)))
        later.reverse()   # popped from the end, oldest first
        connections = self.bag.connections(self.topics - static)
        logged = run.report.logged   # topic: [first, last] log time of its messages
        feeds = {connection.id: run.feed_of(connection.topic) for connection in connections}
        topics = {connection.id: connection.topic for connection in connections}
        window, held = [], 0   # the feed of each message read ahead, and their bytes
        feeding = False   # (an error while feeding is the caller's: not fed again on top)
        try:
            for count, (connection, log_ns, raw) in enumerate(self.bag.messages(connections),
                                                              count + 1):
                while later and later[-1][0] <= log_ns:
                    window.append(later.pop()[1])
                topic = topics[connection.id]
                read[topic] += 1
                if topic in logged:
                    logged[topic][1] = log_ns
                else:
                    logged[topic] = [log_ns, log_ns]
                feed = feeds[connection.id]
                feed.add(raw)
                window.append(feed)
                held += len(raw)
                if held > WINDOW_BYTES or not count % PROGRESS_EVERY:
                    feeding = True
                    _feed_window(window)
                    feeding, held = False, 0
                if on_progress is not None and not count % PROGRESS_EVERY:
                    on_progress(count)
        finally:
            if not feeding:
                _feed_window(window)   # what was read before damaged storage, too
        return count


def _feed_window(window):
    """Feed the messages read ahead in their order (`window`: the feed of each); clear it."""
    feeds = set(window)
    for feed in feeds:
        feed.prepare()
    for feed, messages in groupby(window):
        feed.take(len(list(messages)))
    for feed in feeds:
        feed.clear()
    window.clear()


class _Feed:
    """The raw messages of one topic read ahead (`add`), fed one by one (`on_raw`) in runs."""

    def __init__(self, on_raw):
        self.raws = []
        self.add = self.raws.append
        self.on_raw = on_raw
        self.taken = 0

    def prepare(self):
        """Make ready to feed the messages added (nothing to do here)."""

    def take(self, count):
        """Feed the next `count` messages added."""
        start, self.taken = self.taken, self.taken + count
        for raw in self.raws[start:self.taken]:
            self.on_raw(raw)

    def clear(self):
        """Forget the messages fed."""
        self.raws.clear()
        self.taken = 0


class _StaticFeed:
    """One static TFMessage's transforms, set again where the message is in the bag."""

    def __init__(self, tf, topic, transforms):
        self.tf, self.topic, self.transforms = tf, topic, transforms

    def prepare(self):
        """Nothing to decode."""

    def take(self, count):
        """Set the transforms again (count: 1, a feed per message)."""
        self.tf.restate(self.topic, self.transforms)

    def clear(self):
        """Nothing is held."""


class _PoseFeed(_Feed):
    """A PoseStamped or TransformStamped topic: its messages are decoded together (cdr.py)."""

    def __init__(self, on_raw, on_rows, msgtype, checks=CheckConfig(), stream=LINK):
        super().__init__(on_raw)
        self.on_rows = on_rows   # (raws, cdr.DecodedPoses, start, stop) of decoded rows
        self.msgtype = msgtype
        self.frame_id = checks.frame_id(stream)   # the header frame the checks want ('' any)
        self.max_position_m = checks.max_position_m
        self.decoded = None

    def prepare(self):
        """Decode the messages added."""
        self.decoded = cdr.decode_poses(self.raws, self.msgtype, frame_id=self.frame_id,
                                        max_position_m=self.max_position_m)

    def take(self, count):
        """Feed the next `count` messages: decoded rows together, the others by on_raw."""
        start, self.taken = self.taken, self.taken + count
        for first, stop, ok in cdr.stretches(self.decoded.ok[start:self.taken]):
            if ok:
                self.on_rows(self.raws, self.decoded, start + first, start + stop)
            else:
                for raw in self.raws[start + first:start + stop]:
                    self.on_raw(raw)


# The replay's stream names are the live node's (message_checks), so counts read alike.
STREAMS = {'link': LINK, 'sensor': SENSOR}


class _Run:
    """The state of one replay: the transform tree, the message checks, the report."""

    def __init__(self, replay, session):
        self.replay = replay
        self.session = session
        self.poses = PoseScreen(replay.checks)
        self.report = ReplayReport(
            stamps={'link': [None, None], 'sensor': [None, None]},
            sources={STREAMS[stream]: str(source) for stream, source in replay.inputs.items()})
        self.images = None
        if replay.images is not None:
            replay.images.restart()   # a second run (capture mode fallback) starts afresh
            self.images = ImageInput(replay.images, self.poses,
                                     on_notice=self.report.camera_changes.append)
        self.tree = TfFeed.new_tree(replay.tf_max_gap_ns)
        self.adders = {'link': session.add_link_pose, 'sensor': session.add_sensor_pose}
        self.tf = TfFeed(self.tree, self.poses, {
            stream: tuple(source.frames) for stream, source in replay.inputs.items()
            if source.frames is not None}, self._feed, link='link', sensor='sensor')
        for stream, frames in self.tf.watchers.items():
            self.report.tf_dropped[stream] = frames
            self.report.frames[stream] = tuple(replay.inputs[stream].frames)

    def feed_of(self, topic):
        """Return the _Feed that takes the raw messages of `topic`."""
        if topic in self.replay.tf_topics:
            return _Feed(lambda raw: self.on_tf(topic, raw, static=False))
        if self.replay.inputs['sensor'].camera_info == topic:
            return _Feed(self.on_camera_info)
        stream = next(s for s, source in self.replay.inputs.items() if source.topic == topic)
        on_pose = self._pose_handler(topic, stream)
        msgtype = self.replay.msgtypes[topic]
        if msgtype not in cdr.STRINGS_BEFORE_POSE:
            return _Feed(on_pose)
        return _PoseFeed(on_pose, lambda *rows: self._on_rows(stream, msgtype, *rows), msgtype,
                         self.replay.checks, STREAMS[stream])

    def _pose_handler(self, topic, stream):
        """Return the function that takes one raw pose message (rosbags deserialises it)."""
        msgtype = self.replay.msgtypes[topic]
        deserialize = TYPESTORE.deserialize_cdr
        checked = STREAMS[stream]
        take = (self.poses.take if msgtype not in IMAGE_TYPES
                else lambda _, msg: self.images.take_image(msg))

        def on_pose(raw):
            try:
                msg = deserialize(raw, msgtype)
            except Exception as error:   # noqa: B902 - whatever rosbags raises on bad bytes
                self.poses.stats.note(checked, 0)
                self.poses.bad(checked, 'undecodable', f'{type(error).__name__}: {error}')
                return
            taken = take(checked, msg)
            if taken is not None:
                self._add(stream, taken, msg)
        return on_pose

    def _add(self, stream, taken, msg):
        """Add the pose taken, (stamp_ns, Pose), from message `msg` to the session's `stream`."""
        if self._track(stream, taken[0], taken[0]):
            self.report.frames[stream] = frame_ids(msg)
        self.poses.verdict(STREAMS[stream], self.adders[stream](*taken), held=self.session.held)

    def _on_rows(self, stream, msgtype, raws, decoded, start, stop):
        """Take the decoded poses of raws[start:stop] (cdr.DecodedPoses rows) at once."""
        stamps = decoded.stamps_ns[start:stop].tolist()
        if self._track(stream, stamps[0], stamps[-1]):
            self.report.frames[stream] = frame_ids(
                TYPESTORE.deserialize_cdr(raws[start], msgtype))
        checked = STREAMS[stream]
        self.poses.take_rows(checked, len(stamps))
        self.poses.verdict(checked, self.session.add_poses(
            stream, stamps, decoded.positions[start:stop], decoded.quaternions[start:stop]),
            count=len(stamps), held=self.session.held)

    def _track(self, stream, first_ns, last_ns):
        """Note the stamps of poses fed on `stream`; return whether they are its first."""
        span = self.report.stamps[stream]
        first = span[0] is None
        if first:
            span[0] = first_ns
        span[1] = last_ns
        return first

    def _feed(self, stream, stamp_ns, pose):
        """Feed one pose composed from the TF tree."""
        self._track(stream, stamp_ns, stamp_ns)
        checked = STREAMS[stream]
        self.poses.take_rows(checked, 1)
        self.poses.verdict(checked, self.adders[stream](stamp_ns, pose),
                           held=self.session.held)

    def on_camera_info(self, raw):
        """Take a raw CameraInfo: the intrinsics of the images that follow."""
        try:
            msg = TYPESTORE.deserialize_cdr(raw, CAMERA_INFO_TYPE)
        except Exception as error:   # noqa: B902 - whatever rosbags raises on bad bytes
            self.poses.bad(SENSOR, 'bad_camera_info', f'{type(error).__name__}: {error}')
            return
        held = self.images.first_image.held
        taken = self.images.take_camera_info(msg)
        if taken is not None:   # the image held for the first camera_info
            self._add('sensor', taken, held[0])

    def on_tf(self, topic, raw, static, keep=False):
        """
        Take a raw TFMessage: update the tree, then feed the poses it completes.

        Returns the static transforms stored (TfFeed.take, with `keep`).
        """
        try:
            msg = TYPESTORE.deserialize_cdr(raw, TF_TYPE)
        except Exception as error:   # noqa: B902 - whatever rosbags raises on bad bytes
            self.poses.bad(topic, 'undecodable', f'{type(error).__name__}: {error}')
            return []
        return self.tf.take(topic, msg, static, keep=keep)

    def finish(self, count):
        """Close the TF watchers and return the completed ReplayReport."""
        self.tf.finish()
        if self.images is not None:
            self.images.finish()
        self.poses.verdict(None, self.session.end_streams(), count=0)
        report = self.report
        stats = self.poses.stats
        report.messages = count
        report.bad = Counter(stats.bad)
        report.good = Counter(stats.good)
        report.examples = {key: stats.example(*key) for key in stats.bad}
        report.tf_stale = sum(self.tree.stale.values())
        report.tf_swapped = self.tf.swapped_frames()
        report.tf_frames = tuple(sorted(self.tree.frames))
        report.tree = self.tree
        report.static_tf_topics = tuple(topic for topic in self.replay.tf_topics
                                        if is_static_tf_topic(topic))
        report.static_tf_unread = tuple(topic for topic in sorted(self.replay.bag.topics)
                                        if is_static_tf_topic(topic)
                                        and topic not in self.replay.tf_topics)
        report.counters = self.session.counters
        return report


def frame_warnings(report, setup='eye_in_hand', invert_sensor=False):
    """Return stream.frame_notices' warnings on the frames of the messages the replay used."""
    seen = {checked: report.frames[stream] for stream, checked in STREAMS.items()
            if stream in report.frames}
    return frame_notices.notices(seen, setup, invert_sensor)


def swapped_frames(report, result=None):
    """
    Return TfFeed.swapped_frames' warnings on TF input's link and tracking frames.

    Those the estimate `result` leaves standing (tf_feed.kept_swapped).
    """
    return kept_swapped(report.tf_swapped, result)


# The stamp-to-log-time lags at a stream's two ends agree this well (clock_offset_ns).
LOG_ENDS_NS = 250_000_000


def clock_offset_ns(replay, report):
    """
    Return the offset to add to the sensor stamps that the bag's log times suggest, or None.

    Each stream's header stamps minus the log times of its messages (the recorder's clock),
    at its first and last message, averaged: the two streams' difference is the offset of
    their clocks, to within their latencies (tens of milliseconds). None for TF input, or a
    stream without poses, or one whose two ends disagree by more than LOG_ENDS_NS: the
    stamps are those of the poses used, the log times those of every message, so messages
    skipped at one end (images before the board was seen) part them.
    """
    lag = {}
    for stream, source in replay.inputs.items():
        stamps, logged = report.stamps.get(stream), report.logged.get(source.topic)
        if source.topic is None or not stamps or stamps[0] is None or logged is None:
            return None
        first, last = stamps[0] - logged[0], stamps[1] - logged[1]
        if abs(first - last) > LOG_ENDS_NS:
            return None
        lag[stream] = (first + last) // 2
    return lag['link'] - lag['sensor']


def seen_frames(report, invert_sensor=False):
    """
    Return the frames the replay saw, by easy_handeye2 parameter name (empty ones left out).

    The link poses' base and link frames, the sensor poses' sensor and object frames (a
    PoseStamped names only its header frame: the object's is then unknown).
    """
    base, link = report.frames.get('link', (None, None))
    sensor, seen = report.frames.get('sensor', (None, None))
    if invert_sensor:
        sensor, seen = seen, sensor
    named = {'robot_base_frame': base, 'robot_effector_frame': link,
             'tracking_base_frame': sensor, 'tracking_marker_frame': seen}
    return {key: frame for key, frame in named.items() if frame}


def result_frames(report, setup='eye_in_hand', invert_sensor=False):
    """
    Return (parent, child) frames of the result from what the replay saw; None when unknown.

    Parent: the link frame (eye_in_hand) or the base frame (eye_to_hand); child: the sensor
    frame, the header frame of T_sensor_obj (its child frame with invert_sensor).
    """
    seen = seen_frames(report, invert_sensor)
    return (seen.get('robot_effector_frame' if setup == 'eye_in_hand' else 'robot_base_frame'),
            seen.get('tracking_base_frame'))
