"""
Frame names of the pose messages that contradict what the poses are, or the result's frames.

A link pose is T_base_link: its header.frame_id is the robot base, a transform's child frame
the link. A sensor pose is T_sensor_obj: its header.frame_id is the sensor's frame (with
invert_sensor the object's, and a transform's child frame the sensor's). Nothing in the
motions reveals a pose given in the wrong frame or topics swapped (the equations of swapped
inputs fit exactly, README section 3), but the frame names often do. `notices` compares the
frames of the first message of each stream with each other and with the result's frames
(link_frame -> sensor_frame), and says what looks wrong and what to set. The messages are
used either way: these are warnings, not checks (message_checks refuses messages only
against link_frame_id and sensor_frame_id, when they are set).
"""

from quatcal_ros.stream.message_checks import LINK, SENSOR


def notices(seen, setup, invert_sensor, result_frames=None):
    """
    Return the warnings (texts) the frames `seen` call for.

    seen: {stream: (header.frame_id, child_frame_id or None)} of a message of each stream
    (LINK, SENSOR; frames without a leading slash; a stream may be missing).
    result_frames: the node's (link_frame, sensor_frame) as it publishes them; None where the
    result's frames are taken from the messages themselves (the replay), which leaves only the
    check of the two streams against each other.
    """
    base, link = seen.get(LINK, (None, None))
    sensor_header, sensor_child = seen.get(SENSOR, (None, None))
    sensor = sensor_child if invert_sensor else sensor_header
    said = []
    if base and base == sensor_header and not invert_sensor:
        said.append(
            f'the link poses and the sensor poses are both in frame {base!r} (header.frame_id): '
            'a link pose is the link in the robot base frame, a sensor pose the object in the '
            "sensor's own frame (T_sensor_obj, as a detector publishes it); sensor poses "
            'transformed into the base frame cannot show the mounting')
    if result_frames is None:
        return said
    parent, child = result_frames
    if base and base == child and not said:
        said.append(
            f'link_pose messages are in {base!r}, the sensor frame (sensor_frame): are the '
            'link_pose and sensor_pose topics swapped? Swapped, the equations still fit, and '
            "the answer is the observed object's pose instead of the mounting")
        return said
    if setup == 'eye_in_hand':
        if base and base == parent:
            said.append(
                f'link_pose messages are in {base!r} (header.frame_id), the link itself '
                '(link_frame): a link pose is the link in the robot base frame (T_base_link), '
                "stamped with the base's frame; or, if that is the base, link_frame should "
                'name the link that carries the sensor')
        elif link and link != parent:
            said.append(_renamed(f'link_pose transforms end in {link!r}', 'parent', link,
                                 parent, 'link_frame'))
    elif base and base != parent:
        said.append(_renamed(f'link_pose messages are in {base!r}', 'parent', base, parent,
                             'link_frame'))
    if sensor and sensor != child and sensor != base:
        said.append(_renamed(f'the sensor poses are measured in {sensor!r}', 'child', sensor,
                             child, 'sensor_frame')
                    + ' (unless that is the robot base: then the link_pose and sensor_pose '
                    'topics are swapped)')
    return said


def _renamed(what, role, frame, published, parameter):
    return (f"{what}, so the estimate's {role} frame is {frame!r}, but it is published as "
            f'{published!r} ({parameter}), a frame it does not describe; set '
            f'{parameter}:={frame}')
