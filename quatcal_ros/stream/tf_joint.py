"""
Where the mounting joins a transform tree without giving any frame a second parent.

The calibration gives T_link_sensor for the sensor frame the poses name: with a camera that
is the optical frame, which the camera driver's /tf_static already hangs from camera_link. A
transform, or a URDF joint, link -> optical frame would give it a second parent. The mounting
joins the tree at the top of the sensor frame's static subtree instead (camera_link), composed
with the static chain down to the sensor frame. The node's /tf_static broadcast, the command
it logs on ~/save, and the result file's and the replay's joints all use it; the samples
journal records that chain (static_chain), so that `solve` of a journal gives the same joint.
"""

from dataclasses import dataclass, replace

from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.tf_tree import normalize_frame, TransformTree


@dataclass(frozen=True)
class Joint:
    """The mounting as the edge parent -> child that the tree can take, and why it is that."""

    parent: str
    child: str
    result: object      # the calibration result, its transform that of parent -> child
    note: str = ''      # '' when it is the calibrated frames' edge as the tree takes it
    breaks: str = ''    # why no edge can be added without breaking the tree, or ''


def rerooted(pose, parent, child, tree):
    """
    Return ((parent, root, T_parent_root), None) that gives no frame of `tree` a second parent.

    root: the top of `child`'s static subtree (child itself when it has no parent), the
    mounting T_parent_child (pose.Pose) composed with the static root -> child chain.
    (None, why) when a moving transform holds that subtree, or it is connected to `parent`
    already.
    """
    parent, child = normalize_frame(parent), normalize_frame(child)
    root, refused = _static_root(parent, child, tree)
    if refused:
        return None, refused
    if root == child:
        return (parent, child, pose), None
    return (parent, root, pose @ tree.lookup(root, child, 0).inverse()), None   # any stamp


def _static_root(parent, child, tree):
    """Return (the top of `child`'s static subtree, None), or (None, why no edge fits)."""
    root = child
    while True:
        above = tree.parent(root)
        if above is None or above == parent or not tree.is_static(root):
            break
        root = above
    above = tree.parent(root)
    if above is not None and above != parent:
        return None, (f'{child} hangs from {above} by a moving transform on /tf, so a '
                      f'transform {parent} -> {root} would give {root} a second parent')
    if above is None and tree.chain(root, parent) is not None:
        return None, (f'{root} is already connected to {parent} in TF: another transform '
                      f'{parent} -> {root} would close a loop')
    return root, None


def static_chain(parent, child, tree):
    """
    Return (root, (x, y, z, qx, qy, qz, qw)) of the static root -> child the joint goes by.

    What a samples journal records of the TF tree (files.journal), so that a solve of it gives
    the node's joint (recorded_tree). None when the joint is the calibrated edge itself: no
    tree (pose topics), the child has no static parent, or no edge fits (rerooted's refusals).
    """
    if tree is None:   # (pose topics)
        return None
    parent, child = normalize_frame(parent), normalize_frame(child)
    root, refused = _static_root(parent, child, tree)
    if refused or root == child:
        return None
    found = tree.lookup(root, child, 0)   # (static: any stamp)
    w, x, y, z = (float(value) for value in found.quaternion)
    return root, (*(float(value) for value in found.position), x, y, z, w)


def recorded_tree(child, chain):
    """Return a TransformTree of the one static edge static_chain gave (root -> child)."""
    tree = TransformTree()
    add_static_chain(tree, child, chain)
    return tree


def add_static_chain(tree, child, chain):
    """Put the static edge root -> child that static_chain gave into `tree`."""
    root, (x, y, z, qx, qy, qz, qw) = chain
    tree.set_transform(root, child, 0, Pose.create((x, y, z), (qw, qx, qy, qz)), static=True)


def joint(result, frames, tree=None):
    """
    Return the Joint of calibration `result` (frames: its (parent, child)) in `tree`.

    Without a tree (pose topics) it is the calibrated frames' own edge.
    """
    parent, child = (normalize_frame(frame) for frame in frames)
    if tree is None:
        return Joint(parent, child, result)
    target, refused = rerooted(Pose.create(result.translation, result.quaternion), parent,
                               child, tree)
    if refused:   # the calibrated edge, said to break the tree
        return Joint(parent, child, result, 'added to the TF tree as it was, this joint breaks '
                     f'it: {refused}', breaks=refused)
    _, root, pose = target
    if root == child:
        return Joint(parent, child, result)
    moved = replace(result, quaternion=pose.quaternion, translation=pose.position)
    return Joint(parent, root, moved,
                 f'{child} already hangs from {root} in TF: the mounting composed '
                 f'with the static {root} -> {child}')
