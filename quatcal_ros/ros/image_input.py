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
    gray_from_image_msg, stamp_ns_from_header
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


class FirstImage:
    """
    The latest image before the first camera_info, held for it.

    A camera driver publishes each image and its camera_info, stamped alike, on two topics,
    so the first image often arrives a moment before the first camera_info: held, it is used
    when that camera_info comes, if stamped within MATCH_NS of it; else, and when a newer
    image replaces it, it is an image without a calibration after all. `process(msg,
    stamp_ns)` is the caller's use of an image (with no camera it counts it as such).
    """

    MATCH_NS = 1_000_000_000

    def __init__(self):
        self.held = None   # (message, stamp_ns)

    def take_image(self, sensor, msg, stamp_ns, process):
        """Return process(msg, stamp_ns), or None when the image is held for a camera_info."""
        if sensor.camera is not None:
            return process(msg, stamp_ns)
        replaced, self.held = self.held, (msg, stamp_ns)
        if replaced is not None:
            process(*replaced)   # (still no camera_info: counted as such)
        return None

    def take_camera_info(self, sensor, msg, process):
        """
        Give `sensor` a CameraInfo's calibration (camera_of); return (changed, error, used).

        used: process() of the image held for it, or None.
        """
        held = self.take() if sensor.camera is None else None
        if held is not None and not self._stamped_near(msg, held[1]):
            process(*held)   # (no camera_info yet: counted as such)
            held = None
        changed, error = camera_of(sensor, msg)
        if error is not None:
            self.held = held
            return changed, error, None
        return changed, error, None if held is None else process(*held)

    def take(self):
        """Return the held (message, stamp_ns), or None, and hold nothing."""
        held, self.held = self.held, None
        return held

    @classmethod
    def _stamped_near(cls, camera_info, stamp_ns):
        try:
            return abs(stamp_ns_from_header(camera_info.header) - stamp_ns) <= cls.MATCH_NS
        except ValueError:   # nanosec out of range
            return False


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
        self.first_image = FirstImage()

    def take_camera_info(self, msg):
        """
        Use the calibration of a CameraInfo (counted as bad when it cannot be used).

        Returns (stamp_ns, Pose) of the board in the image held for the first camera_info
        (FirstImage), or None.
        """
        first = self.sensor.camera is None
        text, error, taken = self.first_image.take_camera_info(self.sensor, msg,
                                                               self._board_pose)
        if error is not None:
            self.screen.bad(SENSOR, 'bad_camera_info', error)
            return None
        if text and self.on_notice is not None:
            self.on_notice(text)
        if (first or text) and self.on_new_camera is not None:
            self.on_new_camera(bool(text))
        return taken

    def take_image(self, msg, now_ns=0):
        """
        Return (stamp_ns, Pose) of the board in an image message, or None (counted).

        Before the first camera_info the image is held for it (FirstImage): None.
        """
        stamp_ns = self.screen.take_header(SENSOR, msg.header, now_ns)
        if stamp_ns is None:
            return None
        return self.first_image.take_image(self.sensor, msg, stamp_ns, self._board_pose)

    def finish(self):
        """Count an image still held for a camera_info that never came (the end of a run)."""
        held = self.first_image.take()
        if held is not None:
            self._board_pose(*held)

    def _board_pose(self, msg, stamp_ns):
        """Return (stamp_ns, Pose) of the board in an image whose header passed, or None."""
        _, view = view_of(self.sensor, msg, stamp_ns)
        if not view.ok:
            detail = view.detail
            if view.refused == 'no_camera_info' and self.camera_info_topic:
                detail += (f' on {self.camera_info_topic}: is it published there, or under '
                           'another name (remap camera_info:=...)?')
            self.screen.bad(SENSOR, view.refused, detail)
            return None
        return stamp_ns, view.pose
