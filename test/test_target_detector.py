"""The target_detector node over real DDS: rendered camera images in, board poses out."""

import re

import cv2
from geometry_msgs.msg import PoseWithCovarianceStamped
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import residual_order
from quatcal_ros.ros import conversions
from quatcal_ros.ros.target_detector import TargetDetector
from quatcal_ros.vision.board import parse_board
from quatcal_ros.vision.camera import camera_from
from quatcal_ros.vision.render import Renderer, view_poses
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import qos_profile_sensor_data
from rendered_cell import BOARD, CAMERA, write_board
from ros_harness import harnesses_of, SpinMixin
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Header


class Harness(SpinMixin):
    """A target detector and a driver node (camera_info, images; poses and debug images)."""

    def __init__(self, domain_id, board_file, transport='raw'):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = TargetDetector(context=self.context, parameter_overrides=[
            Parameter('board_file', value=str(board_file)),
            Parameter('image_transport', value=transport)])
        self.driver = rclpy.create_node('camera_driver', context=self.context)
        self.info = self.driver.create_publisher(CameraInfo, 'camera_info',
                                                 qos_profile_sensor_data)
        self.image = (self.driver.create_publisher(CompressedImage, 'image/compressed',
                                                   qos_profile_sensor_data)
                      if transport == 'compressed'
                      else self.driver.create_publisher(Image, 'image', qos_profile_sensor_data))
        self.poses, self.debug = [], []
        self.driver.create_subscription(PoseWithCovarianceStamped, '/target_detector/pose',
                                        self.poses.append, 10)
        self.driver.create_subscription(Image, '/target_detector/debug_image',
                                        self.debug.append, 10)
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: self.image.get_subscription_count()
                        and self.info.get_subscription_count()
                        and self.driver.count_publishers('/target_detector/pose'),
                        what='discovery of the target detector')

    def send_info(self, camera=CAMERA, stamp_s=0):
        self.info.publish(conversions.camera_info_msg(camera, stamp_s * 10 ** 9))

    def send_image(self, gray, stamp_s=100, encoding='mono8'):
        header = Header(frame_id='camera_color_optical_frame')
        header.stamp.sec = stamp_s
        if isinstance(self.image.msg_type(), CompressedImage):
            ok, data = cv2.imencode('.png', gray)
            self.image.publish(CompressedImage(header=header, format='png',
                                               data=data.tobytes()))
            return
        self.image.publish(Image(header=header, height=gray.shape[0], width=gray.shape[1],
                                 encoding=encoding, step=gray.shape[1],
                                 data=gray.tobytes()))


@pytest.fixture
def board_file(tmp_path):
    return write_board(tmp_path)


@pytest.fixture
def make_harness(domain_id):
    yield from harnesses_of(Harness, domain_id)


@pytest.mark.parametrize('transport', ['raw', 'compressed'])
def test_board_poses_with_covariance_from_images(make_harness, board_file, transport):
    h = make_harness(board_file, transport)
    renderer = Renderer(parse_board(BOARD), CAMERA)
    rng = np.random.default_rng(7)
    truths = view_poses(rng, 3, renderer)
    # Before any camera_info an image waits for it; a newer one replaces it: skipped.
    h.send_image(renderer.render(truths[0], rng), stamp_s=99)
    h.send_image(renderer.render(truths[0], rng, noise=2.0, blur_sigma=0.5), stamp_s=100)
    h.spin_until(lambda: h.node.counts['no_camera_info'] == 1, what='a skipped image')
    h.send_info(stamp_s=100)   # the waiting image's: its pose is published
    h.spin_until(lambda: h.poses, what='the pose of the image before the camera_info')
    assert h.poses[0].header.stamp.sec == 100 and h.node.counts['images'] == 2
    for k, truth in enumerate(truths):
        if k:
            h.send_image(renderer.render(truth, rng, noise=2.0, blur_sigma=0.5),
                         stamp_s=100 + k)
        h.spin_until(lambda: len(h.poses) == k + 1, what=f'pose {k}')
        msg = h.poses[-1]
        assert msg.header.frame_id == 'camera_color_optical_frame'
        assert msg.header.stamp.sec == 100 + k
        pose = conversions.pose_from_msg(msg)
        assert np.degrees(quat.angle_between(pose.quaternion, truth.quaternion)) < 0.5
        assert np.linalg.norm(pose.position - truth.position) < 2e-3
        assert np.all(np.linalg.eigvalsh(residual_order(pose.covariance)) > 0)
    h.spin_until(lambda: len(h.debug) >= 3, what='the debug images')
    assert h.debug[-1].encoding == 'bgr8' and h.debug[-1].width == 640


def test_bad_images_and_camera_info_are_counted_and_skipped(make_harness, board_file, capfd):
    h = make_harness(board_file)
    zeros = camera_from(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 'plumb_bob',
                        [0, 0, 0, 0, 0])
    msg = CameraInfo(width=640, height=480, distortion_model='plumb_bob')   # all zeros
    h.info.publish(msg)
    h.spin_until(lambda: h.node.counts['bad_camera_info'] >= 1, what='a bad camera_info')
    assert h.node.camera is None
    h.send_info(zeros)
    h.spin_until(lambda: h.node.camera is not None, what='the camera_info')
    h.send_image(np.full((480, 640), 128, np.uint8))                      # no board
    h.send_image(np.zeros((480, 640), np.uint8), encoding='yuv422')       # unknown encoding
    h.image.publish(Image(height=480, width=640, encoding='mono8', step=640,
                          data=b'\0' * 100))                               # truncated
    h.spin_until(lambda: h.node.counts['no_board'] == 1 and h.node.counts['bad_image'] == 2,
                 what='the bad images counted')
    assert h.poses == [] and h.node.counts['images'] == 3
    # Each reason is logged, the first of each at once (within the test's seconds: not the
    # second bad image, unless this loaded machine took 5 s between them).
    logged = capfd.readouterr().err
    for line in ('bad_camera_info (1 so far)', 'no_board (1 so far)', 'bad_image (1 so far)'):
        assert line in logged, (line, logged)


def test_a_misspelt_parameter_is_refused_a_whole_number_taken(domain_id, board_file):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        # (and a whole number is taken for a real one)
        node = TargetDetector(context=context, parameter_overrides=[
            Parameter('board_file', value=str(board_file)),
            Parameter('max_reprojection_px', value=3)])
        assert node.sensor.checks.max_reprojection_px == 3.0
        node.destroy_node()
        # A value of the wrong type ended in rclpy's traceback.
        for name, value, words in (('max_reprojection_px', 'abc', "a number, not 'abc'"),
                                   ('min_corners', 4.5, 'a whole number, not 4.5')):
            with pytest.raises(ValueError, match=f'^parameter {name} must be {words}$'):
                TargetDetector(context=context, parameter_overrides=[
                    Parameter('board_file', value=str(board_file)),
                    Parameter(name, value=value)])
        with pytest.raises(ValueError, match=r'no such parameter: min_corner \(did you mean '
                                             r'min_corners\?\); `target_detector --help`'):
            TargetDetector(context=context, parameter_overrides=[
                Parameter('board_file', value=str(board_file)),
                Parameter('min_corner', value=6)])
    finally:
        rclpy.shutdown(context=context)


@pytest.mark.parametrize('name, value, words', [
    ('min_corners', 3, 'min_corners must be at least 4 (a board pose needs 4 corners), not 3'),
    ('max_reprojection_px', 0.0, 'max_reprojection_px must be positive, not 0.0'),
    ('min_sharpness', -1.0, 'min_sharpness must be 0 or more, not -1.0'),
])
def test_checks_no_view_can_pass_are_refused_at_start(name, value, words):
    """min_corners 1 once reached OpenCV's solvePnP, which raised out of the image callback."""
    from quatcal_ros.vision.view import Checks
    with pytest.raises(ValueError, match=re.escape(words)):
        Checks(**{name: value})
