"""
The calibrator with sensor_input:=image over real DDS: images in, the mounting on the pixels out.

The mounting is refined on the corners, which are kept across a restart.

A driver node publishes camera_info, link poses (PoseStamped) and images of a ChArUco board
rendered from a known camera and mounting (vision/render.py) at each stop of an eye-in-hand
cell; the node must detect the board, capture a still sample per stop, keep each sample's
corners and publish the estimate with method reprojection within its uncertainty of the truth.
"""

import json
import time

from geometry_msgs.msg import PoseStamped, TransformStamped
from journal_files import write_journal
import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.corners_file import corners_path, read_corners
from quatcal_ros.ros import conversions
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.sim import simulation
from quatcal_ros.stream.settings import ConfigError
from quatcal_ros.vision.board import parse_board
from quatcal_ros.vision.render import cell_views, Renderer, view_poses
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.qos import QoSProfile, ReliabilityPolicy
from rendered_cell import BOARD, CAMERA, camera_info_msg, write_board
from ros_harness import harnesses_of, LATCHED, SpinMixin
from sensor_msgs.msg import CameraInfo, Image
from std_msgs.msg import Header
from visualization_msgs.msg import Marker, MarkerArray

RELIABLE = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
START_NS = 1_700_000_000 * NS_PER_S
STILL_S, LINK_HZ, IMAGE_HZ = 0.8, 25.0, 10.0


class Response:
    """A std_srvs Trigger response stand-in for calling the services' callbacks."""

    success, message = False, ''


class Harness(SpinMixin):
    """A calibrator in image mode and a driver: camera_info, images, link poses."""

    def __init__(self, domain_id, overrides):
        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.node = CalibratorNode(context=self.context, parameter_overrides=[
            Parameter('max_stamp_offset_s', value=0.0), Parameter('sensor_input', value='image'),
            Parameter('still_window_s', value=0.5), *overrides])
        self.driver = rclpy.create_node('camera_and_robot', context=self.context)
        self.info = self.driver.create_publisher(CameraInfo, 'camera_info', RELIABLE)
        self.image = self.driver.create_publisher(Image, 'image', RELIABLE)
        self.link = self.driver.create_publisher(PoseStamped, 'link_pose', RELIABLE)
        self.transforms, self.markers = [], []
        self.links_sent = 0
        self.driver.create_subscription(MarkerArray, '/calibrator/markers', self.markers.append,
                                        LATCHED)
        self.driver.create_subscription(TransformStamped, '/calibrator/transform',
                                        self.transforms.append, LATCHED)
        for node in (self.node, self.driver):
            self.executor.add_node(node)
        self.spin_until(lambda: self.image.get_subscription_count()
                        and self.info.get_subscription_count()
                        and self.link.get_subscription_count(),
                        what='discovery of the calibrator')

    def send_info(self):
        self.info.publish(camera_info_msg())

    def send_stop(self, stamp_ns, link_pose, gray):
        """
        One still stop: link poses at LINK_HZ and the same scene's image at IMAGE_HZ.

        The image subscription is best effort with a short queue (sensor-data QoS, as camera
        drivers publish): each image is received before the next is sent.
        """
        received = self.node.stats.received
        every = int(LINK_HZ / IMAGE_HZ)
        for i in range(int(STILL_S * LINK_HZ)):
            stamp = stamp_ns + int(i * NS_PER_S / LINK_HZ)
            self.link.publish(conversions.pose_stamped_msg(link_pose, stamp, 'base_link'))
            self.links_sent += 1
            if i % every:
                continue
            # The robot's poses come first (as a 500 Hz arm's would): the pairing needs them.
            self.spin_until(lambda: received['link_pose'] >= self.links_sent,
                            what='the link poses received')
            header = Header(frame_id='camera_color_optical_frame',
                            stamp=conversions.time_msg(stamp))
            images = received['sensor_pose']
            self.image.publish(Image(header=header, height=gray.shape[0], width=gray.shape[1],
                                     encoding='mono8', step=gray.shape[1], data=gray.tobytes()))
            self.spin_until(lambda: received['sensor_pose'] > images, what='an image received')


@pytest.fixture
def make_harness(domain_id):
    yield from harnesses_of(Harness, domain_id)


@pytest.fixture
def board_file(tmp_path):
    return write_board(tmp_path)


def test_an_image_before_the_first_camera_info_is_used_when_it_comes(make_harness, board_file):
    # Two subscriptions, as from a camera driver: the first image often comes before the
    # first camera_info, and was counted as bad.
    h = make_harness([Parameter('board_file', value=str(board_file))])
    rng = np.random.default_rng(5)
    renderer = Renderer(parse_board(BOARD), CAMERA)
    gray = renderer.render(view_poses(rng, 1, renderer)[0], rng, noise=1.0)
    header = Header(frame_id='camera_color_optical_frame', stamp=conversions.time_msg(START_NS))
    h.image.publish(Image(header=header, height=gray.shape[0], width=gray.shape[1],
                          encoding='mono8', step=gray.shape[1], data=gray.tobytes()))
    stats = h.node.stats
    h.spin_until(lambda: stats.received['sensor_pose'] == 1, what='the image')
    assert stats.good['sensor_pose'] == 0 and not stats.bad   # waiting for its camera_info
    h.info.publish(conversions.camera_info_msg(CAMERA, START_NS))
    h.spin_until(lambda: stats.good['sensor_pose'] == 1, what='the image used')
    assert not stats.bad and h.node.images.sensor.counts['detected'] == 1


def send_cell(h, n_stops, seed=3, noise=1.5):
    """Drive `n_stops` stops of a rendered cell; return (mounting, stamps of the stops)."""
    rng = np.random.default_rng(seed)
    renderer = Renderer(parse_board(BOARD), CAMERA)
    mounting, _, seen, links = cell_views(rng, renderer, n_stops, distance_m=(0.35, 0.8))
    h.send_info()
    h.spin_until(lambda: h.node.images.sensor.camera is not None, what='the camera_info')
    stamps = []
    for k in range(n_stops):
        stamp = START_NS + k * 2 * NS_PER_S
        h.send_stop(stamp, links[k], renderer.render(seen[k], rng, noise=noise))
        stamps.append(stamp)
    return mounting, stamps


def test_estimate_refined_on_the_corners_of_each_sample(make_harness, board_file, tmp_path):
    samples_file = tmp_path / 'samples.csv'
    result_file = tmp_path / 'calibration.yaml'
    h = make_harness([Parameter('board_file', value=str(board_file)),
                      Parameter('samples_file', value=str(samples_file)),
                      Parameter('result_file', value=str(result_file))])
    mounting, _ = send_cell(h, 8)
    h.spin_until(lambda: len(h.node.session.samples) == 8, what='8 samples')
    h.spin_until(lambda: h.node.result is not None and h.node.result.samples == 8,
                 what='the estimate of 8 samples')
    result = h.node.result
    assert result.method == 'reprojection'
    assert h.node.session.result.method != 'reprojection'   # the pose-based one beside it
    error_deg = np.degrees(quat.angle_between(result.quaternion, mounting.quaternion))
    error_mm = 1e3 * np.linalg.norm(result.translation - mounting.position)
    # Within 4 reported sigmas (the sigmas are RMS error angles / lengths: a few x at most).
    assert error_deg < 4 * result.uncertainty_deg, (error_deg, result.uncertainty_deg)
    assert error_mm < 4 * result.translation_uncertainty_mm, (
        error_mm, result.translation_uncertainty_mm)
    h.spin_until(lambda: h.transforms and np.allclose(
        conversions.pose_from_msg(h.transforms[-1]).position, result.translation, atol=1e-9),
        what='the refined estimate on ~/transform')
    # Every sample kept its corners, in the file beside the journal.
    rows, skipped = read_corners(corners_path(samples_file))
    assert skipped == 0 and len(rows) == 8
    assert {row[0] for row in rows} == {s.stamp_ns for s in h.node.session.samples}
    assert all(len(points) == len(pixels) >= 6 for _, points, pixels in rows)
    diagnosed = h.node.diagnostic_status()
    status = {v.key: v.value for v in diagnosed.values}
    assert status['method'] == 'reprojection'
    # The fit on the pixels: its corners' noise (as the detector finds the rendered corners)
    # and each view's shared error (the robot here is exact: none, or a trace).
    assert 0.05 < float(status['pixel_noise_px']) < 2.0
    assert len(status['view_error_deg'].split()) == len(status['view_error_mm'].split()) == 3
    # camera_info's focal lengths stand: with 8 views their scale is not tested.
    assert status['focal_scale'] == '1' and result.reprojection['focal_evidence'] is None
    # The validation is the fit on the pixels' own: each view against the fit without it.
    assert result.validation['fit'] == 'pixels'
    assert float(status['validation_rms_reprojection_px']) == pytest.approx(
        result.validation['rms_reprojection_px'], rel=1e-5)
    # The message says the published uncertainty, the key's (it said the pose-based one's).
    assert diagnosed.message.startswith(f'estimating: uncertainty {result.uncertainty_deg:.2g} '
                                        'deg'), diagnosed.message
    assert float(status['uncertainty_deg']) == pytest.approx(result.uncertainty_deg, rel=1e-5)
    # Images are not counted as lost (their sensor-data queue of 5 drops frames by design);
    # the link poses' one publisher is.
    assert status['sensor_messages_lost'] == '' and status['link_messages_lost'] == '0'
    # RViz's view of it: the sensor axes where the last sample puts the camera, the samples.
    h.spin_until(lambda: h.markers and len(next(
        m for m in h.markers[-1].markers if m.type == Marker.SPHERE_LIST).points) == 8,
        what='the markers of 8 samples')
    shown = {m.text: m for m in h.markers[-1].markers}
    assert {'sensor x', 'sensor y', 'sensor z', 'rotation uncertainty', 'samples'} <= set(shown)
    assert all(m.header.frame_id == 'base_link' and m.ns == 'quatcal' for m in shown.values())
    camera = h.node.session.samples[-1].link @ Pose.create(result.translation,
                                                           result.quaternion)
    tip = shown['sensor z'].points[1]
    np.testing.assert_allclose([tip.x, tip.y, tip.z],
                               camera.position + 0.1 * camera.rotation[:, 2], atol=1e-9)
    saved = h.node._on_save(None, Response())
    assert saved.success, saved.message
    saved = plain_yaml.load_file(result_file)
    assert saved['method'] == 'reprojection'
    assert saved['reprojection']['pixel_noise_px'] == pytest.approx(
        float(status['pixel_noise_px']), rel=1e-5)
    assert saved['reprojection']['uncertainty_from'] in ('view_blocks', 'view_jackknife')
    assert 0 <= saved['reprojection']['worst_view_sample'] < 8


def test_resumed_session_refines_on_the_corners_it_kept(make_harness, board_file, tmp_path):
    samples_file = tmp_path / 'samples.csv'
    common = [Parameter('board_file', value=str(board_file)),
              Parameter('samples_file', value=str(samples_file))]
    h = make_harness(common)
    send_cell(h, 6)
    h.spin_until(lambda: h.node.result is not None and h.node.result.samples == 6,
                 what='the estimate of 6 samples')
    before = h.node.result
    assert before.method == 'reprojection'
    h.close()
    again = make_harness([*common, Parameter('resume', value=True)])
    assert again.node.result.method == 'refined'   # on the poses until the camera is known
    again.send_info()
    again.spin_until(lambda: again.node.result.method == 'reprojection',
                     what='the estimate on the kept corners')
    resumed = again.node.result
    np.testing.assert_allclose(resumed.translation, before.translation, atol=1e-9)
    reset = again.node._on_reset(None, Response())
    assert reset.success and again.node.result is None
    again.spin_until(lambda: again.markers and again.markers[-1].markers[0].action
                     == Marker.DELETEALL, what='the markers cleared')
    assert again.node.images.sensor.corners == {}


def test_capture_settings_at_runtime_reach_the_image_sensor(make_harness, board_file):
    # Kept with the estimate (no new session), they must still reach the image sensor:
    # continuous capture takes the nearest image, still capture averages a window's.
    h = make_harness([Parameter('board_file', value=str(board_file))])
    sensor = h.node.images.sensor
    assert sensor.average and sensor.half_window_ns == 250_000_000
    done = h.node.set_parameters_atomically([Parameter('capture_mode', value='continuous'),
                                             Parameter('still_window_s', value=0.8)])
    assert done.successful
    assert not sensor.average and sensor.half_window_ns == 400_000_000


def test_image_mode_needs_a_readable_board_file(domain_id, tmp_path, board_file):
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        with pytest.raises(ConfigError, match='board_file'):
            CalibratorNode(context=context, parameter_overrides=[
                Parameter('sensor_input', value='image'),
                Parameter('samples_file', value=str(tmp_path / 's.csv'))])
        (tmp_path / 'bad.yaml').write_text(json.dumps({'type': 'hexagons'}))
        rng = np.random.default_rng(2)
        samples, _ = simulation.samples(rng, simulation.random_cell(rng), 4)
        earlier = write_journal(tmp_path / 's.csv', samples)
        with pytest.raises(ConfigError, match='bad.yaml'):
            CalibratorNode(context=context, parameter_overrides=[
                Parameter('sensor_input', value='image'),
                Parameter('board_file', value=str(tmp_path / 'bad.yaml')),
                Parameter('samples_file', value=str(tmp_path / 's.csv'))])
        # The journal of an earlier session stays where it was (it was moved aside, silently,
        # by a start that then failed).
        assert (tmp_path / 's.csv').read_bytes() == earlier
        assert not list(tmp_path.glob('s.csv.previous-*'))
        # A board's pose in an image is T_camera_board: inverted, a replay's answer was 1.6 km.
        with pytest.raises(ConfigError, match='invert_sensor does not apply to camera images'):
            CalibratorNode(context=context, parameter_overrides=[
                Parameter('sensor_input', value='image'),
                Parameter('board_file', value=str(board_file)),
                Parameter('invert_sensor', value=True),
                Parameter('samples_file', value=str(tmp_path / 's.csv'))])
    finally:
        rclpy.shutdown(context=context)


def test_sim_cell_with_camera_images_drives_the_calibrator_on_the_pixels(
        domain_id, tmp_path, repo_root):
    """sim_cell camera_images:=true, with the robot's pose errors, and sensor_input:=image."""
    from quatcal_ros.ros.sim_cell import SimCell

    board_file = str(repo_root / 'config' / 'sim_board.yaml')
    context = Context()
    rclpy.init(context=context, domain_id=domain_id)
    executor = SingleThreadedExecutor(context=context)
    cell = SimCell(context=context, parameter_overrides=[
        Parameter(name, value=value) for name, value in (
            ('camera_images', True), ('board_file', board_file), ('seed', 4), ('n_stops', 9),
            ('still_s', 1.0), ('move_s', 0.6), ('link_rate_hz', 100.0),
            ('sensor_rate_hz', 10.0), ('link_rotation_noise_deg', 0.1),
            ('link_translation_noise_m', 0.0005))])
    node = CalibratorNode(context=context, parameter_overrides=[
        Parameter('sensor_input', value='image'), Parameter('board_file', value=board_file),
        Parameter('samples_file', value=str(tmp_path / 'samples.csv'))])
    try:
        for each in (cell, node):
            executor.add_node(each)
        deadline = time.monotonic() + 60.0
        while (node.result is None or node.result.samples < 8) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        result = node.result
        assert result is not None and result.samples >= 8, node.session.last_error
        assert result.method == 'reprojection' and result.validation['fit'] == 'pixels'
        # The robot's reported poses are off at each stop: each view's shared error is fitted.
        assert any(result.reprojection['view_error_deg'])
        error_deg = np.degrees(quat.angle_between(result.quaternion,
                                                  cell.cell.mounting.quaternion))
        error_mm = 1e3 * np.linalg.norm(result.translation - cell.cell.mounting.position)
        # Within 4 reported sigmas (RMS error angle and length).
        assert error_deg < 4 * result.uncertainty_deg, (error_deg, result.uncertainty_deg)
        assert error_mm < 4 * result.translation_uncertainty_mm, (
            error_mm, result.translation_uncertainty_mm)
        # An image before the first camera_info waits for it (two subscriptions, as from a
        # camera driver); one is counted when two images come before it, nothing else.
        assert set(node.stats.bad) <= {('sensor_pose', 'no_camera_info')}, node.stats.bad
    finally:
        executor.shutdown()
        cell.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=context)
