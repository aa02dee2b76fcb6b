"""
The result on /tf_static (publish_tf:=true), through a tf2_msgs publisher, frame-safe.

No tf2_ros is needed: the node publishes tf2_msgs/TFMessage on /tf_static with the QoS of
tf2's static broadcasters (reliable, transient local, depth 1), so late listeners get it.

It never gives a frame a second parent. With TF input the node knows the transform tree, and
when the sensor frame already has a parent there (camera_color_optical_frame under
camera_link, from the camera driver's /tf_static), the published transform is link_frame ->
the root of the sensor frame's static subtree (camera_link), the mounting composed with that
static chain; the log says so once. When the sensor frame hangs from a moving transform, or
its root is already connected to the link frame some other way, a transform from link_frame
would break the tree: nothing is published and the reason is in the log and /diagnostics.
An edge from link_frame itself (this node's earlier publication, heard back) is replaced, and
so is one this node broadcast from an earlier parent (the setup changed at runtime): the new
broadcast replaces it for every listener, so it is taken out of the tree first. One that
another publisher's /tf_static contradicts gives way (ros.tf_feed.TfFeed.ours): an estimate
resumed at start is broadcast before the camera driver's latched transform arrives, and gave
the optical frame a second parent for the life of the node; it is broadcast again, re-rooted.
"""

from quatcal_ros.files import exports
from quatcal_ros.ros import conversions
from quatcal_ros.ros.qos import quiet_publisher_events, TF_STATIC_BROADCAST_QOS
from quatcal_ros.stream import tf_joint
from quatcal_ros.stream.tf_tree import normalize_frame
from tf2_msgs.msg import TFMessage


NOT_BROADCAST = 'nothing is broadcast (the result is on ~/transform)'


class StaticTf:
    """The /tf_static output of a node: made on demand, with its state in words."""

    def __init__(self, node):
        self.node = node
        self.publisher = None
        self.problem = None       # why the last estimate was not broadcast
        self.held = None          # ... when it was its own warnings (hold), in brief
        self.said = None          # the last redirection or refusal logged
        self.sent = set()         # (parent, child) edges this node has broadcast
        self.last = None          # (pose, stamp_ns, parent, child) of the last send()
        self.earlier = False      # what is latched is an earlier session's (~/reset)

    def start(self):
        """Make the publisher (once); return True."""
        if self.publisher is None:
            self.publisher = self.node.create_publisher(
                TFMessage, '/tf_static', TF_STATIC_BROADCAST_QOS,
                event_callbacks=quiet_publisher_events())
        return True

    def send(self, pose, stamp_ns, parent, child, tree=None):
        """
        Broadcast T_parent_child (pose.Pose) at stamp_ns, re-rooted in `tree` when needed.

        tree: the node's stream.tf_tree.TransformTree (TF input), or None (pose topics: the
        transform is published as it is).
        """
        if self.publisher is None:
            return
        self.last = (pose, stamp_ns, parent, child)
        target = (parent, child, pose)
        if tree is not None:
            target = self._frame_safe(pose, parent, child, tree)
        if target is None:
            return
        parent, child, pose = target
        self.sent.add((normalize_frame(parent), normalize_frame(child)))
        self.problem = self.held = None
        self.earlier = False
        self.publisher.publish(TFMessage(transforms=[
            conversions.transform_stamped_msg(pose, stamp_ns, parent, child)]))

    def resend(self, tree):
        """Broadcast the last transform sent again, re-rooted in `tree` (its parents changed)."""
        if self.last is not None:
            self.send(*self.last, tree)

    def new_session(self):
        """
        Note that the session started anew (~/reset): what is latched stays until a new estimate.

        Its reasons for holding or refusing were the old estimates'.
        """
        self.problem = self.held = None
        self.earlier = bool(self.sent) and self.last is not None   # (sent, not withdrawn)

    def withdraw(self):
        """
        Replace what this node latched on /tf_static by nothing (publish_tf turned off).

        Listeners that joined before keep the transform (tf2 keeps static transforms); later
        ones no longer get it.
        """
        if self.publisher is not None and self.sent:   # (`sent` stays: ours to replace)
            self.publisher.publish(TFMessage(transforms=[]))
        self.last = None   # (nothing to send again when the tree changes)

    def _frame_safe(self, pose, parent, child, tree):
        """Return (parent, child, pose) that adds no second parent to `tree`, or None."""
        parent, child = normalize_frame(parent), normalize_frame(child)
        for old_parent, old_child in self.sent:   # ours, from another parent: replaced
            if old_parent != parent and tree.parent(old_child) == old_parent:
                tree.remove_edge(old_child)
        target, refused = tf_joint.rerooted(pose, parent, child, tree)
        if target is None:
            return self._refuse(f'publish_tf: {refused}: {NOT_BROADCAST}')
        if target[1] != child:
            self._say(f'publish_tf: {child} already has a parent in TF '
                      f'({tree.parent(child)}): broadcasting {parent} -> {target[1]}, the '
                      f'mounting composed with the static {target[1]} -> {child}')
        return target

    def hold(self, text, brief='the estimate says not to use it', problem=True):
        """
        Broadcast nothing for this estimate, for the reason `text` (logged once).

        brief: the reason in a few words, for the state; problem: False for a wait that is
        part of every session (logged as info, not named as a problem).
        """
        self.problem, self.held = (text if problem else None), brief
        self._say(text, warning=problem)

    def _refuse(self, text):
        self.problem, self.held = text, None
        self._say(text, warning=True)
        return None

    def _say(self, text, warning=False):
        if text != self.said:
            self.said = text
            if warning:   # one call site per severity (rclpy insists)
                self.node.get_logger().warning(text)
            else:
                self.node.get_logger().info(text)

    def state(self, enabled):
        """Return the broadcast state for /diagnostics, and the problem to name (or None)."""
        if not enabled:
            return 'off (publish_tf is false)', None
        if self.held and not self.problem:
            return f'not broadcast yet: {self.held}', None
        if self.problem:
            return f'not broadcast: {self.held or "it would break the TF tree"}', self.problem
        if self.earlier:
            return 'broadcast: the estimate before ~/reset, latched until a new one', None
        if self.last is None:
            return 'nothing broadcast yet: no estimate', None
        return 'broadcast', None


def broadcast_advice(mount):
    """
    Return the log line with the command that broadcasts the mounting `mount`.

    mount: its tf_joint.Joint, which with TF input is under the frames the broadcast uses: a
    sensor frame that already has a parent (the camera driver's camera_link) would get a
    second one.
    """
    if mount.breaks:
        return ('to broadcast the result on /tf_static: no transform can be given without '
                f'breaking the TF tree: {mount.breaks}: {NOT_BROADCAST}')
    return (f'to broadcast the result on /tf_static{f" ({mount.note})" if mount.note else ""}: '
            + exports.static_transform_publisher_command(mount.result, mount.parent,
                                                         mount.child))
