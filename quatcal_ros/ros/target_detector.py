"""
ROS 2 node `target_detector`: the calibration board's pose in each camera image.

Subscribes `image` (sensor_msgs/Image; CompressedImage on `image/compressed` with
image_transport:=compressed) and `camera_info` (sensor_msgs/CameraInfo), both sensor-data QoS.
For each image it finds the board of `board_file` (vision/detect.py: sub-pixel corners, planar
PnP, the per-view checks) and publishes:
- `~/pose` (geometry_msgs/PoseWithCovarianceStamped): T_camera_board with the image's header
  (stamp, camera frame), the covariance from the PnP Jacobian at the pixel noise its residuals
  show, in ROS's order; the calibrator takes it with sensor_pose_type:=pose_with_covariance,
  other tools as any PoseWithCovarianceStamped;
- `~/debug_image` (sensor_msgs/Image, bgr8, with debug_image:=true): the image with the
  corners found and the board's axes drawn, while something subscribes to it.
A refused view (no board, too few corners, blurred, an ambiguous or badly fitting pose) and a
bad message (an unknown encoding, a truncated image, a CameraInfo of zeros) are counted by
reason, logged at most every 5 s per reason, and skipped.
"""

import time

import cv2
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.ros import command_line, conversions, spin
from quatcal_ros.ros.image_input import FirstImage, view_of
from quatcal_ros.ros.qos import quiet_publisher_events
from quatcal_ros.stream.log_throttle import LogThrottle
from quatcal_ros.vision.board import read_board
from quatcal_ros.vision.image_sensor import ImageSensor
from quatcal_ros.vision.view import Checks
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import CameraInfo, CompressedImage, Image

NODE_NAME = 'target_detector'
TRANSPORTS = ('raw', 'compressed')
# name: (default, description); read once at start (read-only).
PARAMETERS = {
    'board_file': ('', 'the board.yaml of the calibration target (required)'),
    'image_transport': ('raw', 'raw: sensor_msgs/Image on image; compressed: '
                        'sensor_msgs/CompressedImage on image/compressed'),
    'debug_image': (True, 'publish ~/debug_image with the corners and axes drawn'),
    'min_corners': (Checks.min_corners, 'fewest corners a view must show'),
    'max_reprojection_px': (Checks.max_reprojection_px,
                            'largest RMS corner residual of a usable pose (pixels)'),
    'min_sharpness': (Checks.min_sharpness,
                      'least variance of the Laplacian over the board region (blur check)'),
}


class TargetDetector(Node):
    """The `target_detector` node (module docstring); ValueError on bad parameters."""

    def __init__(self, **kwargs):
        super().__init__(NODE_NAME, **kwargs)
        command_line.accept_integers_for_reals(self, {
            name: Parameter.Type.DOUBLE for name, (default, _) in PARAMETERS.items()
            if type(default) is float})
        values = {name: command_line.declared(
            self, name, default, ParameterDescriptor(description=text, read_only=True))
            for name, (default, text) in PARAMETERS.items()}
        command_line.refuse_unknown_parameters(self, PARAMETERS, NODE_NAME, ValueError)
        if values['image_transport'] not in TRANSPORTS:
            raise ValueError(f'image_transport must be one of {TRANSPORTS}, not '
                             f'{values["image_transport"]!r}')
        if not values['board_file']:
            raise ValueError('board_file is required: the board.yaml of the target')
        try:
            self.board = read_board(values['board_file'])
        except BadInputError as error:
            raise ValueError(str(error)) from None
        self._throttle = LogThrottle()   # one refusal line per reason at most every 5 s
        # The calibrator's own image sensor: the same checks, camera and counts.
        self.sensor = ImageSensor(self.board, Checks(
            min_corners=int(values['min_corners']),
            max_reprojection_px=float(values['max_reprojection_px']),
            min_sharpness=float(values['min_sharpness'])))
        self.first_image = FirstImage()   # an image before the first camera_info, held for it
        self.pose_publisher = self.create_publisher(
            PoseWithCovarianceStamped, '~/pose', 10, event_callbacks=quiet_publisher_events())
        self.debug_publisher = (self.create_publisher(Image, '~/debug_image', 2,
                                                      event_callbacks=quiet_publisher_events())
                                if values['debug_image'] else None)
        self.create_subscription(CameraInfo, 'camera_info', self._on_camera_info,
                                 qos_profile_sensor_data)
        compressed = values['image_transport'] == 'compressed'
        images = self.create_subscription(CompressedImage if compressed else Image,
                                          'image/compressed' if compressed else 'image',
                                          self._on_image, qos_profile_sensor_data)
        self.get_logger().info(f'detecting a {self.board.kind} board '
                               f'({self.board.size[0]} x {self.board.size[1]}) in '
                               f'{images.topic_name}')

    @property
    def camera(self):
        """Return the vision.camera.Camera of the last usable camera_info, or None."""
        return self.sensor.camera

    @property
    def counts(self):
        """Return the images by outcome: 'images', 'detected' and each refusal's reason."""
        return self.sensor.counts

    def _on_camera_info(self, msg):
        text, error, _ = self.first_image.take_camera_info(self.sensor, msg, self._detect)
        if error is not None:
            self._log('bad_camera_info', str(error))
        elif text:
            self.get_logger().info('camera_info changed: new intrinsics from now on')

    def _on_image(self, msg):
        try:
            stamp_ns = conversions.stamp_ns_from_header(msg.header)
        except ValueError as error:   # nanosec out of range
            self.counts['images'] += 1
            self.counts['bad_image'] += 1
            self._log('bad_image', str(error))
            return
        self.first_image.take_image(self.sensor, msg, stamp_ns, self._detect)

    def _detect(self, msg, stamp_ns):
        """Publish the board pose in an image (and the debug image when watched)."""
        gray, view = view_of(self.sensor, msg, stamp_ns)
        if not view.ok:
            self._log(view.refused, view.detail)
            if gray is None or view.refused == 'no_camera_info':
                return
        else:
            self.pose_publisher.publish(conversions.pose_with_covariance_stamped_msg(
                view.pose, stamp_ns, msg.header.frame_id))
        if self.debug_publisher is not None and self.debug_publisher.get_subscription_count():
            self.debug_publisher.publish(conversions.image_msg(   # (drawn when watched)
                self._drawn(gray, view), msg.header))

    def _drawn(self, gray, view):
        image = cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR)
        if view.image_points is not None:
            for u, v in view.image_points:
                cv2.circle(image, (int(round(u)), int(round(v))), 3, (0, 255, 0), 1)
        if view.ok:   # the board's axes x red, y green, z blue
            length = 0.5 * min(self.board.extent_m)
            ends, _ = cv2.projectPoints(np.vstack([np.zeros(3), length * np.eye(3)]),
                                        cv2.Rodrigues(view.pose.rotation)[0],
                                        view.pose.position, self.camera.K, self.camera.D)
            # Clipped to the image here: cv2.drawFrameAxes logged a warning for every frame
            # whose axes left it (a board near the edge).
            origin, *tips = np.clip(np.rint(ends.reshape(-1, 2)), -1e6, 1e6).astype(int)
            height, width = image.shape[:2]
            for tip, colour in zip(tips, ((0, 0, 255), (0, 255, 0), (255, 0, 0))):
                inside, start, end = cv2.clipLine((0, 0, width, height), tuple(origin.tolist()),
                                                  tuple(tip.tolist()))
                if inside:
                    cv2.line(image, start, end, colour, 2)
        return image

    def _log(self, reason, detail):
        if self._throttle.due(reason, time.monotonic()) is not None:
            self.get_logger().warning(f'{reason} ({self.counts[reason]} so far): {detail}')


def command_line_problem(arguments):
    """Return (exit status, text) for --help or a command line the detector must not start with."""
    def help_text():
        return command_line.help_text(
            NODE_NAME, 'The calibration board in camera images: its pose on ~/pose for the '
            "calibrator (sensor_pose_type:=pose_with_covariance beside a robot's PoseStamped).",
            [(name, default, text) for name, (default, text) in PARAMETERS.items()])
    return command_line.problem(arguments, help_text, PARAMETERS)


def main(args=None):
    """Run the target detector; return 2 (after logging the reason) for bad parameters."""
    return spin.run(TargetDetector, NODE_NAME, (ValueError, ParameterException),
                    'invalid parameters', args,
                    command_line_problem)


if __name__ == '__main__':
    raise SystemExit(main())
