"""
Camera messages in, board poses out: the one image path of the live node and the replay.

`ImageInput` takes sensor_msgs CameraInfo and Image / CompressedImage messages (rclpy's or
rosbags': the fields are the same), checks each image's header as a pose message's
(pose_screen.PoseScreen.take_header), converts it to grayscale and lets the
vision.image_sensor.ImageSensor find the board. A view that cannot be used is counted on the
sensor stream under its reason (IMAGE_REASONS) and skipped, like a malformed pose message.
"""

from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.ros.conversions import BadImageError, camera_from_camera_info, \
    gray_from_image_msg
from quatcal_ros.stream.message_checks import SENSOR
from quatcal_ros.vision.view import REASONS as VIEW_REASONS, View

# Why an image gave no sensor pose: the detector's reasons and the messages' own.
IMAGE_REASONS = {
    **VIEW_REASONS,
    'bad_image': 'an image that cannot be decoded (unknown encoding, truncated data)',
    'bad_camera_info': 'a camera_info that is not a usable calibration (zeros, wrong sizes)',
    'no_camera_info': 'an image before any usable camera_info',
}


def camera_of(sensor, msg):
    """
    Give `sensor` the calibration of a CameraInfo message; return (changed, error).

    changed: ImageSensor.set_camera's sentence ('' for the first or the same intrinsics);
    error: why the message is no usable calibration (counted as 'bad_camera_info'), or None.
    """
    try:
        camera = camera_from_camera_info(msg)
    except BadInputError as error:
        sensor.counts['bad_camera_info'] += 1
        return '', error
    return sensor.set_camera(camera), None


def view_of(sensor, msg, stamp_ns):
    """
    Return (grayscale image or None, view.View) of an image message stamped `stamp_ns`.

    An image that does not decode is a View refused as 'bad_image', counted like the others.
    """
    try:
        gray = gray_from_image_msg(msg)
    except BadImageError as error:
        sensor.counts['images'] += 1
        sensor.counts['bad_image'] += 1
        return None, View(refused='bad_image', detail=str(error))
    return gray, sensor.view(stamp_ns, gray)


class ImageInput:
    """Camera messages to the sensor poses of a session (module docstring)."""

    def __init__(self, sensor, screen, on_notice=None, on_new_camera=None):
        """
        Count the messages through `screen`; find the board with `sensor`.

        :param sensor: vision.image_sensor.ImageSensor.
        :param screen: the PoseScreen that counts the sensor stream's messages.
        :param on_notice: on_notice(text) for what the user should know (new intrinsics).
        :param on_new_camera: on_new_camera(changed) after the first camera_info (False) and
            new intrinsics (True).
        """
        self.sensor = sensor
        self.screen = screen
        self.on_notice = on_notice
        self.on_new_camera = on_new_camera
        self.camera_info_topic = None   # the live node's, named when none has come

    def take_camera_info(self, msg):
        """Use the calibration of a CameraInfo (counted as bad when it cannot be used)."""
        first = self.sensor.camera is None
        text, error = camera_of(self.sensor, msg)
        if error is not None:
            self.screen.bad(SENSOR, 'bad_camera_info', error)
            return
        if text and self.on_notice is not None:
            self.on_notice(text)
        if (first or text) and self.on_new_camera is not None:
            self.on_new_camera(bool(text))

    def take_image(self, msg, now_ns=0):
        """Return (stamp_ns, Pose) of the board in an image message, or None (counted)."""
        stamp_ns = self.screen.take_header(SENSOR, msg.header, now_ns)
        if stamp_ns is None:
            return None
        _, view = view_of(self.sensor, msg, stamp_ns)
        if not view.ok:
            detail = view.detail
            if view.refused == 'no_camera_info' and self.camera_info_topic:
                detail += (f' on {self.camera_info_topic}: is it published there, or under '
                           'another name (remap camera_info:=...)?')
            self.screen.bad(SENSOR, view.refused, detail)
            return None
        return stamp_ns, view.pose
