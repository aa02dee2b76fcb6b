"""Tests of stream.tf_joint: where the mounting joins a TF tree without a second parent."""

from dataclasses import dataclass

import numpy as np
from numpy.testing import assert_allclose

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.stream.tf_joint import joint, recorded_tree, static_chain
from quatcal_ros.stream.tf_tree import TransformTree

OPTICAL = Pose.create([0.01, 0.02, 0.0], [0.5, -0.5, 0.5, -0.5])   # camera_link -> optical
MOUNTING = Pose.create([0.1, -0.02, 0.2], quat.from_rotation_vector([0.3, -0.2, 0.1]))


@dataclass(frozen=True)
class Result:
    """What joint() reads of a CalibrationResult."""

    quaternion: np.ndarray
    translation: np.ndarray


RESULT = Result(MOUNTING.quaternion, MOUNTING.position)


def driver_tree():
    """Return the robot on /tf and the camera driver's camera_link -> optical (static)."""
    tree = TransformTree()
    tree.set_transform('base_link', 'tool0', 0, Pose.identity())
    tree.set_transform('camera_link', 'optical', 0, OPTICAL, static=True)
    return tree


def test_without_a_tree_or_a_parent_the_joint_is_the_calibrated_edge():
    assert joint(RESULT, ('tool0', 'optical')) == (
        joint(RESULT, ('tool0', 'optical'), TransformTree()))
    mount = joint(RESULT, ('tool0', 'optical'))
    assert (mount.parent, mount.child, mount.note, mount.breaks) == ('tool0', 'optical', '', '')
    assert mount.result is RESULT


def test_a_sensor_frame_with_a_static_parent_joins_at_the_top_of_its_static_subtree():
    mount = joint(RESULT, ('tool0', '/optical'), driver_tree())   # (tf1's leading slash)
    assert (mount.parent, mount.child, mount.breaks) == ('tool0', 'camera_link', '')
    assert mount.note == ('optical already hangs from camera_link in TF: the mounting '
                          'composed with the static camera_link -> optical')
    joined = Pose.create(mount.result.translation, mount.result.quaternion)
    back = joined @ OPTICAL   # T_tool0_camera_link T_camera_link_optical = the mounting
    assert_allclose(back.position, MOUNTING.position, atol=1e-12)
    assert np.degrees(quat.angle_between(back.quaternion, MOUNTING.quaternion)) < 1e-9


def test_a_joint_that_would_break_the_tree_says_so():
    moving = driver_tree()
    moving.set_transform('shoulder', 'camera_link', 0, Pose.identity())   # on /tf
    mount = joint(RESULT, ('tool0', 'optical'), moving)
    assert (mount.parent, mount.child) == ('tool0', 'optical') and mount.result is RESULT
    assert mount.breaks == ('optical hangs from shoulder by a moving transform on /tf, so a '
                            'transform tool0 -> camera_link would give camera_link a second '
                            'parent')
    assert mount.note.startswith('added to the TF tree as it was, this joint breaks it: ')
    loop = driver_tree()   # the robot placed in the camera's frame: camera_link -> base_link
    loop.set_transform('camera_link', 'base_link', 0, Pose.identity(), static=True)
    mount = joint(RESULT, ('tool0', 'optical'), loop)
    assert 'would close a loop' in mount.breaks, mount


def test_the_static_chain_a_journal_records_gives_the_same_joint_again():
    tree = driver_tree()
    root, values = static_chain('tool0', '/optical', tree)
    assert root == 'camera_link'
    assert_allclose(values[:3], OPTICAL.position, atol=1e-15)
    assert_allclose(values[3:], quat.xyzw_from_wxyz(OPTICAL.quaternion), atol=1e-15)
    again = joint(RESULT, ('tool0', 'optical'), recorded_tree('optical', (root, values)))
    mount = joint(RESULT, ('tool0', 'optical'), tree)
    assert (again.parent, again.child, again.note) == (mount.parent, mount.child, mount.note)
    assert_allclose(again.result.translation, mount.result.translation, atol=1e-15)
    assert_allclose(again.result.quaternion, mount.result.quaternion, atol=1e-15)


def test_no_static_chain_where_the_joint_is_the_calibrated_edge():
    assert static_chain('tool0', 'optical', None) is None              # pose topics
    assert static_chain('tool0', 'camera_link', driver_tree()) is None   # no parent
    moving = driver_tree()
    moving.set_transform('shoulder', 'camera_link', 0, Pose.identity())
    assert static_chain('tool0', 'optical', moving) is None            # would break the tree
