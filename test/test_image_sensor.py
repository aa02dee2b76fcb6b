"""The image input shared by the node and the replay: corners, their file, a bag replay."""

import json
import re
from types import SimpleNamespace

import numpy as np
import pytest
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Sample
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.corners_file import corners_path, CornersFile, read_corners
from quatcal_ros.ros import bag, conversions
from quatcal_ros.stream.session import SessionConfig
from quatcal_ros.tools.cli import _sensor_input, replay_main
from quatcal_ros.vision.board import parse_board
from quatcal_ros.vision.camera import camera_from
from quatcal_ros.vision.image_sensor import ImageSensor, mean_corners
from quatcal_ros.vision.render import cell_views, Renderer, view_poses
from rendered_cell import BOARD, CAMERA, write_board

MS = 1_000_000


def points(*xs):
    return np.array([[x, 0.0, 0.0] for x in xs])


def test_mean_corners_averages_each_corner_seen_by_most_views():
    views = [(points(0.0, 0.03), np.array([[10.0, 20.0], [30.0, 40.0]])),
             (points(0.0, 0.03, 0.06), np.array([[12.0, 22.0], [32.0, 42.0], [50.0, 60.0]])),
             (points(0.03, 0.0), np.array([[34.0, 44.0], [14.0, 24.0]]))]
    object_points, pixels = mean_corners(views)
    by_x = dict(zip(object_points[:, 0].round(3).tolist(), pixels.tolist()))
    assert by_x == {0.0: [12.0, 22.0], 0.03: [32.0, 42.0]}   # 0.06: one view of three


def sensor_with_views(capture_mode='auto'):
    capture = type(SessionConfig().capture)(mode=capture_mode, window_ns=500 * MS)
    sensor = ImageSensor(parse_board(BOARD), session_config=SessionConfig(capture=capture))
    sensor.camera = CAMERA
    for k, stamp in enumerate((1000, 1100, 1200, 1300, 1400, 2500)):
        sensor._recent.append((stamp * MS, points(0.0, 0.03, 0.06, 0.09),
                               np.array([[10.0 + k, 0.0], [20.0 + k, 0.0], [30.0, 0.0],
                                         [40.0, 0.0]])))
    return sensor


def test_a_still_sample_keeps_the_mean_of_its_window_and_continuous_the_nearest_view():
    still = sensor_with_views('auto')
    assert still.keep(Sample(1200 * MS, None, None))
    np.testing.assert_allclose(still.corners[1200 * MS][1][:2], [[12.0, 0.0], [22.0, 0.0]])
    assert not still.keep(Sample(1900 * MS, None, None))    # no view within 250 ms
    moving = sensor_with_views('continuous')
    assert moving.keep(Sample(1290 * MS, None, None))
    np.testing.assert_allclose(moving.corners[1290 * MS][1][:2], [[13.0, 0.0], [23.0, 0.0]])
    # Views that share fewer than 4 corners leave the sample without corners, not broken.
    sparse = sensor_with_views('auto')
    sparse._recent.clear()
    sparse._recent.extend([(1000 * MS, points(0.0), np.zeros((1, 2))),
                           (1100 * MS, points(0.03), np.zeros((1, 2))),
                           (1200 * MS, points(0.06), np.zeros((1, 2)))])
    assert not sparse.keep(Sample(1100 * MS, None, None)) and sparse.corners == {}


def test_new_intrinsics_drop_the_corners_measured_with_the_old_ones():
    sensor = sensor_with_views()
    assert sensor.set_camera(CAMERA) == ''
    sensor.keep(Sample(1200 * MS, None, None))
    other = camera_from(640, 480, [[610, 0, 320], [0, 610, 240], [0, 0, 1]], 'plumb_bob',
                        [0, 0, 0, 0, 0])
    assert 'corners of 1 sample(s) and 6 view(s) of the still window' in sensor.set_camera(other)
    assert sensor.corners == {}


def test_the_corners_file_reads_back_exactly_skips_a_torn_line_and_moves_aside(tmp_path):
    path = corners_path(tmp_path / 'samples.csv')
    assert path.name == 'samples.corners.jsonl'
    pixels = np.array([[1 / 3, 2 / 7], [np.pi, np.e]])
    written = CornersFile(path, resume=False)
    written.append(5, points(0.0, 0.1 / 3), pixels)
    written.sync()
    written.close()
    with open(path, 'a') as file:
        file.write('{"stamp_ns": 6, "points": [[0.0, ')   # a crash mid-line
    rows, skipped = read_corners(path)
    assert skipped == 1 and rows[0][0] == 5
    assert np.array_equal(rows[0][2], pixels) and np.array_equal(rows[0][1], points(0, 0.1 / 3))
    resumed = CornersFile(path, resume=True)
    assert len(resumed.restored) == 1 and 'unreadable' in resumed.messages[0][1]
    resumed.append(7, points(0.0), pixels[:1])   # after the torn tail was cut off
    resumed.close()
    rows, skipped = read_corners(path)
    assert skipped == 0 and [row[0] for row in rows] == [5, 7]
    fresh = CornersFile(path, resume=False)
    assert fresh.restored == [] and 'moved to' in fresh.messages[0][1]
    fresh.close()
    assert path.read_text() == '' and len(list(tmp_path.glob('*.previous-*'))) == 1


# --- replay of a bag with camera images -----------------------------------------------------

def image_msg(stamp_ns, gray, encoding='mono8'):
    kind = bag.TYPESTORE.types['sensor_msgs/msg/Image']
    header = conversions._header(stamp_ns, 'camera_optical', bag.TYPESTORE)
    return kind(header=header, height=gray.shape[0], width=gray.shape[1], encoding=encoding,
                is_bigendian=0, step=gray.shape[1], data=np.frombuffer(gray.tobytes(), np.uint8))


def camera_info_msg(stamp_ns, focal_scale=1.0):
    types = bag.TYPESTORE.types
    K = CAMERA.K.copy()
    K[0, 0] *= focal_scale
    K[1, 1] *= focal_scale
    roi = types['sensor_msgs/msg/RegionOfInterest'](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    return types['sensor_msgs/msg/CameraInfo'](
        header=conversions._header(stamp_ns, 'camera_optical', bag.TYPESTORE),
        height=CAMERA.height, width=CAMERA.width, distortion_model='plumb_bob',
        d=np.zeros(5), k=K.ravel().astype(float), r=np.eye(3).ravel(),
        p=np.zeros(12), binning_x=0, binning_y=0, roi=roi)


def write_image_bag(path, n_stops, seed=4, bad_every=0, info_after=False, changed_at=None):
    """
    Write a stop-and-go eye-in-hand bag: 50 Hz link poses, 10 Hz images at each stop.

    Each image's camera_info is logged just before it, or just after it (`info_after`); that
    of image number `changed_at` (from 1) has focal lengths 1 % longer.
    """
    rng = np.random.default_rng(seed)
    renderer = Renderer(parse_board(BOARD), CAMERA)
    mounting, _, seen, links = cell_views(rng, renderer, n_stops, distance_m=(0.35, 0.8))
    messages, images = [], 0
    for k in range(n_stops):
        start = (1_700_000_000 + 2 * k) * NS_PER_S
        gray = renderer.render(seen[k], rng, noise=1.5)
        for i in range(40):   # 0.8 s still
            stamp = start + i * 20 * MS
            messages.append(('/robot/pose', stamp, conversions.pose_stamped_msg(
                links[k], stamp, 'base_link', bag.TYPESTORE)))
            if i % 5 == 2:
                images += 1
                bad = bad_every and images % bad_every == 0
                messages.append(('/camera/color/camera_info', stamp + (3 if info_after else 1),
                                 camera_info_msg(stamp, 1.01 if images == changed_at else 1.0)))
                messages.append(('/camera/color/image_raw', stamp + 2,
                                 image_msg(stamp, gray, 'yuv422' if bad else 'mono8')))
    bag.write_bag(path, {'/robot/pose': 'geometry_msgs/msg/PoseStamped',
                         '/camera/color/image_raw': 'sensor_msgs/msg/Image',
                         '/camera/color/camera_info': 'sensor_msgs/msg/CameraInfo'}, messages)
    return mounting


@pytest.fixture
def board_file(tmp_path):
    return write_board(tmp_path)


def test_replay_of_camera_images_refines_on_the_corners(tmp_path, board_file, capsys):
    mounting = write_image_bag(tmp_path / 'cell', 8, bad_every=7)
    status = replay_main([str(tmp_path / 'cell'), '--link-topic', '/robot/pose',
                          '--image-topic', '/camera/color/image_raw',
                          '--board-file', str(board_file), '--still-window-s', '0.5',
                          '--quiet', '--report', str(tmp_path / 'report.html'),
                          '--result-out', str(tmp_path / 'calibration.yaml')])
    out = capsys.readouterr()
    assert status == 0, out.err
    result = json.loads(out.out)
    assert result['method'] == 'reprojection' and result['samples'] == 8
    assert result['pose_based_method'] == 'refined'
    assert result['views']['used'] == 8 and result['views']['counts']['bad_image'] == 64 // 7
    assert any('bad_image' in text for text in result['warnings'])
    # The fit on the pixels with every key it had when the tools added it beside the result.
    assert {'rotation', 'translation', 'uncertainty_deg', 'translation_uncertainty_mm',
            'uncertainty_from', 'model_uncertainty_deg', 'model_translation_uncertainty_mm',
            'pixel_noise_px', 'reprojection_rms_px', 'worst_view_rms_px', 'converged',
            'iterations'} <= set(result['reprojection'])
    saved = plain_yaml.load_file(tmp_path / 'calibration.yaml')   # the answer printed
    assert saved['reprojection'] == result['reprojection']
    assert saved['method'] == 'reprojection'
    assert saved['translation']['x'] == pytest.approx(result['translation']['x'], abs=1e-12)
    page = (tmp_path / 'report.html').read_text()
    assert 'reprojection' in page and page.count('<svg') == 4
    q = result['rotation']
    error_deg = np.degrees(quat.angle_between(
        quat.wxyz_from_xyzw([q['x'], q['y'], q['z'], q['w']]), mounting.quaternion))
    t = np.array([result['translation'][k] for k in 'xyz'])
    error_mm = 1e3 * np.linalg.norm(t - mounting.position)
    assert error_deg < 4 * result['uncertainty_deg'], (error_deg, result['uncertainty_deg'])
    assert error_mm < 4 * result['translation_uncertainty_mm'], (
        error_mm, result['translation_uncertainty_mm'])


def test_samples_taken_in_motion_weigh_the_time_offset_against_the_answer_printed(
        tmp_path, board_file, capsys):
    # The hint quoted the pose-based uncertainty beside the answer on the pixels.
    write_image_bag(tmp_path / 'cell', 8)
    assert replay_main([str(tmp_path / 'cell'), '--link-topic', '/robot/pose',
                        '--image-topic', '/camera/color/image_raw', '--board-file',
                        str(board_file), '--capture', 'continuous', '--quiet']) == 0
    result = json.loads(capsys.readouterr().out)
    assert result['method'] == 'reprojection'
    (moving,) = [w for w in result['warnings'] if 'taken while the link turned' in w]
    assert f'(the uncertainty: {result["uncertainty_deg"]:.2g} deg)' in moving, moving


def test_a_bag_whose_first_image_comes_before_its_camera_info_uses_it(tmp_path, board_file,
                                                                      capsys):
    write_image_bag(tmp_path / 'cell', 6, info_after=True)
    assert replay_main([str(tmp_path / 'cell'), '--link-topic', '/robot/pose',
                        '--image-topic', '/camera/color/image_raw', '--board-file',
                        str(board_file), '--still-window-s', '0.5', '--quiet']) == 0
    counts = json.loads(capsys.readouterr().out)['views']['counts']
    assert counts['images'] == counts['detected'] == 6 * 8 and 'no_camera_info' not in counts


def test_a_camera_info_that_changes_is_said_with_the_views_it_cost(tmp_path, board_file,
                                                                   capsys):
    # The corners measured with the old intrinsics are dropped: 4 of 8 views went without a
    # word in a replay (the live node logs it).
    write_image_bag(tmp_path / 'cell', 6, changed_at=14)
    assert replay_main([str(tmp_path / 'cell'), '--link-topic', '/robot/pose',
                        '--image-topic', '/camera/color/image_raw', '--board-file',
                        str(board_file), '--still-window-s', '0.5', '--quiet']) == 0
    warnings = json.loads(capsys.readouterr().out)['warnings']
    (said,) = [w for w in warnings if w.startswith('camera_info changed')]
    first = re.match(r'camera_info changed 2 times; the first: camera_info changed \(new '
                     r'intrinsics\): the corners of (\d+) sample\(s\) and (\d+) view\(s\) of '
                     'the still window were measured with the old ones', said)
    assert first and int(first[1]) + int(first[2]) > 0, said


def test_images_are_fed_in_windows_of_bounded_bytes(tmp_path, board_file, capsys,
                                                    monkeypatch):
    """The read-ahead window of 512 messages held 3 GB of 1080p images: it is cut by bytes."""
    write_image_bag(tmp_path / 'cell', 6)
    argv = [str(tmp_path / 'cell'), '--link-topic', '/robot/pose', '--image-topic',
            '/camera/color/image_raw', '--board-file', str(board_file), '--still-window-s',
            '0.5', '--quiet']
    answers = []
    for window_bytes in (bag.WINDOW_BYTES, 1):   # 1: every message fed on its own
        monkeypatch.setattr(bag, 'WINDOW_BYTES', window_bytes)
        assert replay_main(argv) == 0
        answers.append(json.loads(capsys.readouterr().out))
    assert answers[0] == answers[1] and answers[0]['samples'] == 6


def test_replay_of_images_names_what_is_missing(tmp_path, board_file, capsys):
    write_image_bag(tmp_path / 'cell', 3)
    base = [str(tmp_path / 'cell'), '--link-topic', '/robot/pose', '--quiet']
    assert replay_main([*base, '--image-topic', '/camera/color/image_raw']) == 2
    assert '--board-file' in capsys.readouterr().err
    assert replay_main([*base, '--image-topic', '/camera/color/image_raw', '--board-file',
                        str(board_file), '--camera-info-topic', '/nope']) == 2
    assert ('no topic /nope (camera calibration; another topic: --camera-info-topic)'
            in capsys.readouterr().err)
    assert replay_main([*base, '--image-topic', '/camera/color/camera_info', '--board-file',
                        str(board_file)]) == 2
    assert 'has type sensor_msgs/msg/CameraInfo' in capsys.readouterr().err
    # A board without images: refused (it was ignored, the poses of --sensor-topic used).
    assert replay_main([*base, '--sensor-topic', '/robot/pose', '--board-file',
                        str(board_file)]) == 2
    assert '--board-file goes with --image-topic' in capsys.readouterr().err
    assert replay_main([*base, '--image-topic', '/camera/color/image_raw', '--board-file',
                        str(board_file), '--invert-sensor']) == 2
    assert 'invert_sensor does not apply to camera images' in capsys.readouterr().err


def test_a_second_run_of_the_images_starts_afresh():
    # The replay's fallback pass (continuous capture) reran the images with the counts and
    # the camera of the first pass: 24 images of a 12-image bag, and intrinsics the bag only
    # gives later.
    sensor = ImageSensor(parse_board(BOARD))
    sensor.counts['images'] += 12
    sensor.camera = object()
    sensor.corners[5] = (points(0.0, 0.03, 0.06, 0.09), np.zeros((4, 2)))
    sensor.restart()
    assert sensor.counts == {} and sensor.camera is None and sensor.corners == {}


@pytest.mark.parametrize('image, info', [
    ('/camera/color/image_raw', '/camera/color/camera_info'),
    ('/camera/color/image_raw/compressed', '/camera/color/camera_info'),
    ('image', 'camera_info')])
def test_the_camera_info_beside_an_image_topic_or_its_transport(board_file, image, info):
    # For image_transport's /compressed topic it looked beside the transport:
    # /camera/color/image_raw/camera_info
    args = SimpleNamespace(image_topic=image, camera_info_topic=None,
                           board_file=str(board_file), sensor_topic=None, sensor_frames=None,
                           invert_sensor=False)
    source, _ = _sensor_input(bag, args, None)
    assert source.camera_info == info


def test_new_intrinsics_start_the_corners_file_over(tmp_path, board_file):
    from quatcal_ros.ros.image_samples import ImageSamples
    from quatcal_ros.stream.settings import DEFAULTS, session_config, Settings
    config = Settings.from_values({**DEFAULTS, 'sensor_input': 'image',
                                   'board_file': str(board_file),
                                   'samples_file': str(tmp_path / 'samples.csv')})
    images = ImageSamples(config, session_config(config), tmp_path / 'samples.csv')
    images.sensor.corners[5] = (points(0.0, 0.03, 0.06, 0.09), np.zeros((4, 2)))
    assert images.keep([Sample(5, None, None)]) == [] and images.sync() == []
    assert len(read_corners(corners_path(tmp_path / 'samples.csv'))[0]) == 1
    (level, text), = images.camera_changed()
    assert level == 'warning' and 'starts over' in text
    assert read_corners(corners_path(tmp_path / 'samples.csv'))[0] == []
    assert len(list(tmp_path.glob('samples.corners.jsonl.previous-*'))) == 1
    images.close()


def test_a_last_record_without_its_newline_is_kept(tmp_path):
    path = tmp_path / 'samples.corners.jsonl'
    path.write_text('{"stamp_ns": 5, "points": [[0, 0, 0]], "pixels": [[1, 2]]}\n'
                    '{"stamp_ns": 6, "points": [[0, 0, 0]], "pixels": [[3, 4]]}')
    resumed = CornersFile(path, resume=True)
    assert [row[0] for row in resumed.restored] == [5, 6]
    resumed.append(7, points(0.0), np.zeros((1, 2)))
    resumed.close()
    assert [row[0] for row in read_corners(path)[0]] == [5, 6, 7]


def image_input(board=BOARD):
    """Return (ImageInput with the camera_info topic named, its PoseScreen)."""
    from quatcal_ros.ros.image_input import ImageInput
    from quatcal_ros.ros.pose_screen import PoseScreen
    screen = PoseScreen()
    images = ImageInput(ImageSensor(parse_board(board)), screen)
    images.camera_info_topic = '/camera/color/camera_info'
    return images, screen


def test_the_image_before_the_first_camera_info_waits_for_it():
    # A driver publishes an image and its camera_info on two topics: the first image often
    # came first and was counted as an image without a calibration.
    images, screen = image_input()
    rng = np.random.default_rng(3)
    renderer = Renderer(parse_board(BOARD), CAMERA)
    truth = view_poses(rng, 1, renderer)[0]
    gray = renderer.render(truth, rng, noise=1.0)
    start = 1_700_000_000 * NS_PER_S
    assert images.take_image(image_msg(start, gray)) is None
    assert screen.stats.bad == {}                                   # held, not counted
    assert images.take_image(image_msg(start + 100 * MS, gray)) is None
    # A newer image replaces it: the first is an image without a calibration after all, and
    # the message says where the node listens for one.
    assert screen.stats.bad == {('sensor_pose', 'no_camera_info'): 1}
    assert screen.stats.example('sensor_pose', 'no_camera_info') == (
        'no usable camera_info received yet on /camera/color/camera_info: is it published '
        'there, or under another name (remap camera_info:=...)?')
    # A camera_info that is no calibration leaves it waiting; the one stamped as it uses it.
    zeros = camera_info_msg(start + 100 * MS)
    zeros.k[:] = 0.0
    assert images.take_camera_info(zeros) is None
    stamp_ns, pose = images.take_camera_info(camera_info_msg(start + 100 * MS))
    assert stamp_ns == start + 100 * MS
    assert np.degrees(quat.angle_between(pose.quaternion, truth.quaternion)) < 0.5
    assert images.sensor.counts == {'images': 2, 'no_camera_info': 1, 'detected': 1,
                                    'bad_camera_info': 1}
    assert screen.stats.bad[('sensor_pose', 'no_camera_info')] == 1

    # A camera_info stamped far from the held image (a driver that stamps it 0, another
    # camera's): the image was taken without one.
    images, screen = image_input()
    images.take_image(image_msg(start, gray))
    assert images.take_camera_info(camera_info_msg(0)) is None
    assert screen.stats.bad == {('sensor_pose', 'no_camera_info'): 1}
    assert images.sensor.camera is not None
    # An image still held when the run ends is counted: nothing is lost silently.
    images, screen = image_input()
    images.take_image(image_msg(start, gray))
    images.finish()
    assert screen.stats.bad == {('sensor_pose', 'no_camera_info'): 1}
