"""The result on /tf_static: never a second parent, and its own earlier broadcast replaced."""

from quatcal_ros.core.pose import Pose
from quatcal_ros.ros.static_tf import StaticTf
from quatcal_ros.stream.tf_tree import TransformTree

OPTICAL = Pose.create([0.01, 0.02, 0.0], [0.5, -0.5, 0.5, -0.5])   # camera_link -> optical
MOUNTING = Pose.create([0.1, 0.0, 0.2], [1.0, 0.0, 0.0, 0.0])


class Node:
    """What StaticTf needs of a node: a logger (itself, saying nothing)."""

    def get_logger(self):
        return self

    def info(self, text):
        pass

    def warning(self, text):
        pass


class Publisher:
    def __init__(self):
        self.sent = []

    def publish(self, msg):
        self.sent.append([(t.header.frame_id, t.child_frame_id) for t in msg.transforms])


def test_a_new_parent_replaces_the_nodes_own_earlier_broadcast():
    # The setup changed at runtime (eye_in_hand -> eye_to_hand): the node's own
    # tool0 -> camera_link, heard back on /tf_static, once made it refuse base_link ->
    # camera_link as a second parent, and the stale transform stayed.
    tree = TransformTree()
    tree.set_transform('base_link', 'tool0', 0, Pose.identity())   # the robot, moving
    tree.set_transform('camera_link', 'camera_optical', 0, OPTICAL, static=True)
    static = StaticTf(Node())
    static.publisher = Publisher()
    static.send(MOUNTING, 1, 'tool0', 'camera_optical', tree)
    assert static.publisher.sent[-1] == [('tool0', 'camera_link')]
    tree.set_transform('tool0', 'camera_link', 1, Pose.identity(), static=True)   # heard back
    static.send(MOUNTING, 2, 'base_link', 'camera_optical', tree)
    assert static.publisher.sent[-1] == [('base_link', 'camera_link')]
    assert static.problem is None


def test_a_moving_parent_of_someone_else_is_still_refused():
    tree = TransformTree()
    tree.set_transform('shoulder', 'camera_link', 0, Pose.identity())   # dynamic, not ours
    tree.set_transform('camera_link', 'camera_optical', 0, OPTICAL, static=True)
    static = StaticTf(Node())
    static.publisher = Publisher()
    static.send(MOUNTING, 1, 'base_link', 'camera_optical', tree)
    assert not static.publisher.sent and 'second parent' in static.problem


def test_turned_off_the_latched_transform_is_withdrawn():
    # publish_tf:=false left the last transform latched on /tf_static for new listeners
    static = StaticTf(Node())
    static.withdraw()                       # nothing made, nothing sent: nothing to do
    static.publisher = Publisher()
    static.withdraw()
    assert static.publisher.sent == []
    static.send(MOUNTING, 1, 'tool0', 'camera')
    static.withdraw()
    assert static.publisher.sent == [[('tool0', 'camera')], []]


def test_the_nodes_own_edge_gives_way_whichever_comes_first():
    # The driver's camera_link -> optical came before the node's own tool0 -> optical was
    # heard back (sent before the driver's came): ours was counted as breaking the tree and
    # stayed latched for every other listener.
    from quatcal_ros.ros import conversions
    from quatcal_ros.ros.pose_screen import PoseScreen
    from quatcal_ros.ros.tf_feed import TfFeed
    from tf2_msgs.msg import TFMessage

    def message(parent, child, pose):
        return TFMessage(transforms=[conversions.transform_stamped_msg(pose, 1, parent, child)])
    for driver_first in (True, False):
        screen, replaced = PoseScreen(), []
        feed = TfFeed(TfFeed.new_tree(), screen, {}, lambda *pose: None)
        feed.ours, feed.on_ours_replaced = {('tool0', 'camera_optical')}, \
            lambda: replaced.append(True)
        ours, theirs = (message('tool0', 'camera_optical', MOUNTING),
                        message('camera_link', 'camera_optical', OPTICAL))
        for msg in ((theirs, ours) if driver_first else (ours, theirs)):
            feed.take('/tf_static', msg, static=True)
        assert feed.tree.parent('camera_optical') == 'camera_link', driver_first
        assert replaced == [True] and not screen.stats.bad and not feed.ours, driver_first
