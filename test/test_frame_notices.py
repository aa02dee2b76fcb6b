"""Tests of stream/frame_notices.py: what the frame names of the pose messages give away."""

import pytest
from quatcal_ros.stream.frame_notices import notices
from quatcal_ros.stream.message_checks import LINK, SENSOR

NODE = ('tool0', 'camera')   # the node's default result frames, eye-in-hand


def seen(link, sensor):
    return {LINK: link, SENSOR: sensor}


@pytest.mark.parametrize('setup, frames, result', [
    # A robot driver's and a detector's usual frames, the result named alike
    ('eye_in_hand', seen(('base_link', None), ('camera', None)), NODE),
    ('eye_in_hand', seen(('base_link', 'tool0'), ('camera', 'marker')), NODE),
    ('eye_to_hand', seen(('world', 'tool0'), ('camera', 'marker')), ('world', 'camera')),
    # Frames not known (empty) or a stream not heard yet (TF input: its frames are the
    # settings' own)
    ('eye_in_hand', seen(('', None), ('', None)), NODE),
    ('eye_in_hand', {SENSOR: ('camera', None)}, NODE),
    ('eye_in_hand', {}, NODE),
])
def test_frames_that_agree_call_for_nothing(setup, frames, result):
    assert notices(frames, setup, False, result) == []


def test_both_streams_in_one_frame():
    said = notices(seen(('world', None), ('world', None)), 'eye_in_hand', False, NODE)
    assert len(said) == 1 and "both in frame 'world'" in said[0]
    # The replay (result frames from the messages) says it too, and only it.
    assert notices(seen(('world', None), ('world', None)), 'eye_in_hand', False) == said
    # Inverted sensor poses are stamped in the object's frame, which may be the base's.
    assert notices(seen(('world', None), ('world', 'camera')), 'eye_in_hand', True, NODE) == []


def test_link_poses_in_the_sensor_frame_suggest_swapped_topics():
    said = notices(seen(('camera', None), ('base_link', None)), 'eye_in_hand', False, NODE)
    assert len(said) == 1 and 'topics swapped?' in said[0]
    said = notices(seen(('camera', None), ('base_link', None)), 'eye_to_hand', False,
                   ('base_link', 'camera'))
    assert len(said) == 1 and 'topics swapped?' in said[0]


def test_link_poses_stamped_in_the_link_itself():
    said = notices(seen(('tool0', None), ('camera', None)), 'eye_in_hand', False, NODE)
    assert len(said) == 1 and "link_pose messages are in 'tool0'" in said[0]
    assert 'T_base_link' in said[0]


@pytest.mark.parametrize('setup, link, result, parameter, frame', [
    ('eye_in_hand', ('base_link', 'flange'), NODE, 'link_frame', 'flange'),
    ('eye_to_hand', ('world', 'tool0'), ('base_link', 'camera'), 'link_frame', 'world'),
])
def test_a_parent_frame_other_than_the_published_one(setup, link, result, parameter, frame):
    (said,) = notices(seen(link, ('camera', None)), setup, False, result)
    assert f"the estimate's parent frame is {frame!r}, but it is published as " \
        f'{result[0]!r} ({parameter})' in said and said.endswith(f'set {parameter}:={frame}')


@pytest.mark.parametrize('invert, sensor', [
    (False, ('camera_color_optical_frame', None)),
    (False, ('camera_color_optical_frame', 'marker')),
    (True, ('marker', 'camera_color_optical_frame')),   # inverted: the child is the sensor
])
def test_a_sensor_frame_other_than_the_published_one(invert, sensor):
    (said,) = notices(seen(('base_link', None), sensor), 'eye_in_hand', invert, NODE)
    assert "the sensor poses are measured in 'camera_color_optical_frame'" in said
    assert said.endswith('set sensor_frame:=camera_color_optical_frame (unless that is the '
                         'robot base: then the link_pose and sensor_pose topics are swapped)')
    # The replay names the result after the messages: nothing to say there.
    assert notices(seen(('base_link', None), sensor), 'eye_in_hand', invert) == []
