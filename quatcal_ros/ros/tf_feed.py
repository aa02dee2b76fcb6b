"""
TF messages in, link and sensor poses out: the one TF input of the live node and the replay.

A `TfFeed` keeps a stream.tf_tree.TransformTree of everything on /tf and /tf_static and, for
each stream, a tf_tree.FramePoses of its two frames (link: robot base -> effector; sensor:
tracking base -> marker). Each tf2_msgs/TFMessage (an rclpy message or a rosbags one: the
fields are the same) updates the tree; every pose a stream's chain can now be evaluated at
(at the stamps its dynamic transforms arrived, interpolated, never across a gap, never
"latest") goes to `on_pose(stream, stamp_ns, pose)`. A malformed transform (NaN, a zero or
bad stamp, a stamp beyond max_stamp_offset_s of the node clock, a position beyond
max_position_m, an empty frame id, a loop or a frame with a second parent) is counted under
the TF topic and its reason by the PoseScreen, and skipped, like a malformed pose message.
The first parent a frame is seen with stays its parent (tf2 would re-parent it, silently
moving every frame below it).
"""

from quatcal_ros.core.conventions import PREFIX as CONVENTION_WARNING
from quatcal_ros.ros.conversions import BadPoseError, pose_from_msg, stamp_ns_from_header
from quatcal_ros.stream import message_checks, tf_joint
from quatcal_ros.stream.tf_tree import FramePoses, normalize_frame, TransformTree, TreeError

DEFAULT_TF_TOPICS = ('/tf', '/tf_static')
# Dynamic transforms are interpolated across gaps up to this long (a slow publisher of a fixed
# frame on /tf still works); the pairing applies its own gap limit to the composed poses.
TF_MAX_GAP_NS = 500_000_000
# Dynamic transforms kept per edge (the stretch of stamps): enough for publishers' latencies,
# small enough for robots with many joints at 1 kHz.
TF_CACHE_NS = 2_000_000_000
# A transform this much older than its edge's newest means the clock jumped back (a bag
# played again), and clears the dynamic transforms; a later one, up to this late, is only
# late (a slow publisher, a burst after a stall) and is inserted in order. The cache length:
# anything inside it can still be interpolated.
TF_TIME_JUMP_NS = TF_CACHE_NS
# Frames named in a problem's text, at most.
MAX_FRAMES_NAMED = 12
# The start of TfFeed.swapped_frames' warnings: {what} is 'link' or 'tracking'.
SWAPPED = 'TF input: the {} frames look swapped'
TRACKING_SWAPPED = SWAPPED.format('tracking')
# From this many samples the frame-convention check tells inverted sensor poses (what swapped
# tracking frames give) from right ones: with 3, none of 20 cells warned; with 4, all 20.
CONVENTION_DECIDES_SAMPLES = 5


def kept_swapped(warnings, result):
    """
    Return TfFeed.swapped_frames' `warnings` that estimate `result` (or None) leaves standing.

    The tracking frames' goes when the estimate fits the sensor poses as composed (usable,
    without a frame-convention warning, from enough samples for that check to tell): the
    detector publishes the camera under the marker on purpose.
    """
    fits = (result is not None and result.usable
            and result.samples >= CONVENTION_DECIDES_SAMPLES
            and not any(text.startswith(CONVENTION_WARNING) for text in result.warnings))
    return [text for text in warnings if not (fits and text.startswith(TRACKING_SWAPPED))]


def is_static_tf_topic(topic):
    """Return whether `topic` carries static transforms (/tf_static, or a remapping of it)."""
    return topic.rstrip('/').endswith('tf_static')


class TfFeed:
    """The transform tree, each stream's frame pair, and what to do with a composed pose."""

    @staticmethod
    def new_tree(max_gap_ns=TF_MAX_GAP_NS):
        """Return a stream.tf_tree.TransformTree with the TF input's cache and time jumps."""
        return TransformTree(cache_ns=TF_CACHE_NS, max_gap_ns=max_gap_ns,
                             time_jump_ns=TF_TIME_JUMP_NS)

    def __init__(self, tree, screen, frames, on_pose, link=None, sensor=None):
        """
        Watch `frames` ({stream: (target, source)}) in `tree`; feed poses to `on_pose`.

        screen: the ros.pose_screen.PoseScreen that counts bad transforms; link, sensor: the
        streams of `frames` that are the link pose (robot base -> effector) and the sensor pose
        (camera -> marker), whose frames `problems` checks against the tree's order.
        """
        self.tree = tree
        self.screen = screen
        self.on_pose = on_pose
        self.link, self.sensor = link, sensor
        # The static edges this node broadcast itself (ros.static_tf.StaticTf.sent), heard
        # back: another publisher's parent for their child replaces them, and then
        # on_ours_replaced() is called (the node broadcasts again, under that parent).
        self.ours = set()
        self.on_ours_replaced = None
        # Children whose static edge a resumed journal gave (assume_static_chain), until a
        # /tf_static transform to them comes.
        self.assumed = set()
        self.watchers = {stream: FramePoses(tree, *pair) for stream, pair in frames.items()}

    def assume_static_chain(self, child, chain):
        """
        Hold a journal's static chain above `child` (tf_joint.static_chain) in the tree.

        Any /tf_static transform to `child` replaces it (under its own parent, as the camera
        driver's chain may have more frames), and on_ours_replaced() is called: the joint the
        node broadcasts follows the tree.
        """
        tf_joint.add_static_chain(self.tree, child, chain)
        self.assumed.add(normalize_frame(child))

    def swapped_frames(self, result=None):
        """
        Return a warning for each frame pair given the wrong way round in the tree: [] if none.

        The link's effector frame given is an ancestor of its base frame given, or the marker
        frame of the sensor's camera frame. A pose composes either way (its inverse), so
        nothing else shows it: swapped link frames looked like the other setup (the
        frame-convention check advised it), swapped tracking frames like inverted sensor
        poses, whose positions take the rotation noise times the distance (no still sample).
        A detector may publish the camera under the marker on purpose, though: once the
        estimate `result` fits the tracking frames as given, they are not said to look
        swapped (kept_swapped says when).
        """
        return kept_swapped(self._swapped(), result)

    def _swapped(self):
        found = []
        for stream, what, base, tip, names in (
                (self.link, 'link', 'base', 'effector',
                 'a link pose is the effector in the robot base frame (base {}, effector {}?)'),
                (self.sensor, 'tracking', 'camera', 'marker',
                 'a sensor pose is the marker in the camera frame (tracking_base_frame {}, '
                 'tracking_marker_frame {}?), unless the detector publishes the camera under '
                 'the marker on purpose')):
            watcher = self.watchers.get(stream)
            if watcher is None or watcher.source not in self.tree.path_to_root(
                    watcher.target)[1:]:
                continue
            found.append(f'{SWAPPED.format(what)}: the {base} frame given, {watcher.target}, '
                         f'hangs below the {tip} frame given, {watcher.source}, in the TF '
                         'tree; ' + names.format(watcher.source, watcher.target))
        return found

    def take(self, topic, msg, static, now_ns=0, keep=False):
        """
        Take one TFMessage from `topic` (static: from /tf_static); feed what it completes.

        now_ns: the node clock, for the stamp check of the pose topics (0: none, offline).
        keep: static edges that have a value keep it (TransformTree.set_transform).
        Returns the static transforms stored, [(parent, child, stamp_ns, Pose)].
        """
        changed, stored_static, replaced = [], [], False
        for transform in msg.transforms:
            try:
                stamp_ns = stamp_ns_from_header(transform.header)
                if not static and not self.screen.stamp_ok(topic, stamp_ns, now_ns):
                    continue   # (a static transform holds at any time, its stamp aside)
                pose = pose_from_msg(transform)
                if self.screen.placed(topic, stamp_ns, pose) is None:
                    continue
                parent = normalize_frame(transform.header.frame_id)
                child = normalize_frame(transform.child_frame_id)
                if not parent or not child:
                    raise TreeError(f'a transform {parent!r} -> {child!r} with an empty frame '
                                    'id (tf2 refuses it)')
                if static and child in self.assumed:   # the journal's, until this came
                    self.assumed.discard(child)
                    self.tree.remove_edge(child)
                    replaced = True
                known = self.tree.parent(child)
                if known is not None and known != parent:
                    # Ours against another publisher's, in either order (a resumed estimate
                    # is broadcast before the camera driver's /tf_static comes, or after it
                    # but heard back later): theirs stands, ours is broadcast again.
                    ours = [edge for edge in ((parent, child), (known, child))
                            if static and edge in self.ours]
                    if not ours:
                        raise TreeError(f'{parent!r} -> {child!r} would give {child!r} a '
                                        f'second parent (it has {known!r}): two publishers '
                                        'disagree')
                    self.ours.discard(ours[0])
                    replaced = True
                    if ours[0][0] == parent:
                        continue   # (theirs is in the tree already)
                    self.tree.remove_edge(child)
                stored = self.tree.set_transform(parent, child, stamp_ns, pose, static, keep)
            except TreeError as error:
                self.screen.bad(topic, 'breaks_tree', error)
                continue
            except BadPoseError as error:   # named by its frames: /tf carries many
                self.screen.bad(topic, message_checks.pose_error_reason(error),
                                f'{transform.header.frame_id} -> {transform.child_frame_id}: '
                                f'{error}')
                continue
            except ValueError as error:   # nanosec out of range
                self.screen.bad(topic, 'bad_stamp', error)
                continue
            if not stored:   # older than the edge's buffer: too late to interpolate
                self.screen.bad(topic, 'out_of_order', lambda child=child, stamp=stamp_ns: (
                    f'transform to {child} stamped {stamp * 1e-9:.3f} s is older than the '
                    f'{TF_CACHE_NS * 1e-9:g} s of transforms kept for it'))
            elif static:
                stored_static.append((parent, child, stamp_ns, pose))
            else:
                changed.append((child, stamp_ns))
        for stream, frames in self.watchers.items():
            for child, stamp_ns in changed:
                frames.note(child, stamp_ns)
            for stamp_ns, pose in frames.ready():
                self.on_pose(stream, stamp_ns, pose)
        if replaced and self.on_ours_replaced is not None:
            self.on_ours_replaced()
        return stored_static

    def restate(self, topic, transforms):
        """Set static transforms that `take` returned again, as they came (a later value)."""
        for parent, child, stamp_ns, pose in transforms:
            try:
                self.tree.set_transform(parent, child, stamp_ns, pose, static=True)
            except TreeError as error:
                self.screen.bad(topic, 'breaks_tree', error)

    def problems(self, result=None):
        """
        Return sentences naming each frame pair that cannot be composed from the tree.

        And those of swapped_frames (`result`: the latest estimate, or None).
        """
        found = []
        frames = self.tree.frames
        # Seen from others: not the node's own broadcast heard back, nor a journal's edge.
        heard = self.tree.frames_without(self.assumed | {child for _, child in self.ours})
        for watcher in self.watchers.values():
            target, source = watcher.target, watcher.source
            if self.tree.chain(target, source) is not None:
                continue
            unknown = [frame for frame in (target, source) if frame not in frames]
            seen = ', '.join(sorted(heard)[:MAX_FRAMES_NAMED]) or 'none'
            if unknown:
                why = (f'no frame {" or ".join(unknown)} on /tf or /tf_static yet (frames '
                       f'seen: {seen}{", ..." if len(heard) > MAX_FRAMES_NAMED else ""})')
            else:
                why = self.tree.disconnection(target, source)
            found.append(f'TF input: {target} -> {source} cannot be composed: {why}')
        return found + self.swapped_frames(result)

    def finish(self):
        """Close the frame watchers (what they still wait for is counted as dropped)."""
        for frames in self.watchers.values():
            frames.finish()
