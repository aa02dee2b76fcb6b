"""
The one table of settings: every user-facing setting of the node, the replay and the solver.

Each `Setting` has a name, a default, a unit, its allowed values (a range or choices), a
description and whether it is read-only in the live node.  Everything else is made from it:

- the node's parameters and their descriptors (ros/parameters.py),
- the params file config/calibrator.yaml (`params_file_text`; a test keeps them equal),
- the command-line options of `solve` and `replay` (tools/options.py),
- the core's configuration: `session_config` (SessionConfig) and `check_config` (what pose
  messages must satisfy).

`Settings` holds one checked value per setting (plain Python numbers and strings); it is the
only place where a default is chosen.  The core's configurations (CalibrationOptions,
CaptureConfig, CheckConfig, PlanLimits, ...) restate them as their own defaults for callers
without settings (`calibrate(samples)`); a test keeps the two equal.  Names mean one thing
everywhere: min_motion_deg is the smallest motion the calibration uses (and the step of
continuous capture unless continuous_step_deg is set); how far the link must depart from the
last sample before the next still capture is derived from the still bands
(`session_config`).
"""

from dataclasses import asdict, dataclass, field, make_dataclass
import math
import os

from quatcal_ros.core.calibration import CalibrationOptions, METHODS
from quatcal_ros.core.planner import PlanLimits
from quatcal_ros.core.units import DEFAULT_FRAMES, ns_from_s, plain_number, position_problem, \
    SETUPS
from quatcal_ros.core.validation import Thresholds
from quatcal_ros.stream.capture import CaptureConfig, MODES as CAPTURE_MODES
from quatcal_ros.stream.message_checks import CheckConfig, LINK, SENSOR
from quatcal_ros.stream.pairing import PairingConfig
from quatcal_ros.stream.session import SessionConfig
from quatcal_ros.stream.tf_tree import frame_problem, normalize_frame

DEFAULT_RESULT_FILE = '~/.ros/quatcal/calibration.yaml'
DEFAULT_SAMPLES_FILE = '~/.ros/quatcal/samples.csv'
POSE_TYPES = ('pose', 'transform', 'pose_with_covariance')
PAIRS = ('all', 'consecutive')
SENSOR_INPUTS = ('pose', 'image')
# The pose of a board found in an image is always T_camera_board: nothing to invert (inverted,
# a replay's answer came out 1.6 km long, with exit 0).
IMAGES_NOT_INVERTED = ('invert_sensor does not apply to camera images: the board pose found in '
                       'an image is always the board in the camera frame')
IMAGE_TRANSPORTS = ('raw', 'compressed')
NODE_NAME = 'calibrator'


class ConfigError(ValueError):
    """A setting value that cannot be used; the message names the setting and says why."""


@dataclass(frozen=True)
class Setting:
    """One setting: its default (whose type is the setting's type) and allowed values."""

    name: str
    default: object
    description: str
    unit: str = ''
    choices: tuple = ()
    low: float = None
    high: float = None
    read_only: bool = False
    allow_empty: bool = False
    # Also an option of these command-line tools (tools/options.py), beside the node.
    tools: tuple = ()

    @property
    def constraints(self):
        """Return the allowed values as text ('one of: a, b', '0.05 to 10 s')."""
        if self.choices:
            return 'one of: ' + ', '.join(self.choices)
        if self.low is not None:
            return f'{self.low:g} to {self.high:g}' + (f' {self.unit}' if self.unit else '')
        return ''

    def check(self, value):
        """Return why `value` is not allowed, or None when it is."""
        kind = type(self.default)
        if kind is bool:
            return None if isinstance(value, bool) else f'must be true or false, not {value!r}'
        if kind is int:
            if isinstance(value, bool) or not isinstance(value, int):
                return f'must be a whole number, not {value!r}'
            return self._check_range(value)
        if kind is float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                return f'must be a number, not {value!r}'
            return self._check_range(value)
        if not isinstance(value, str):
            return f'must be a string, not {value!r}'
        if self.choices and value not in self.choices:
            return f'must be one of {", ".join(self.choices)}, not {value!r}'
        if not value.strip() and not (self.allow_empty and value == ''):
            return 'must not be empty' + (" (or '' for any)" if self.allow_empty else '')
        return None

    def _check_range(self, value):
        if not math.isfinite(value) or not self.low <= value <= self.high:
            low, high = (str(limit) if isinstance(limit, int) else f'{limit:g}'
                         for limit in (self.low, self.high))   # (2147483647, not 2.14748e+09)
            return f'must be between {low} and {high}, not {value!r}'
        return None

    def plain(self, value):
        """Return `value` as the setting's type (an integer given for a float setting)."""
        return float(value) if type(self.default) is float else value


SOLVE, REPLAY, PLAN = ('solve',), ('replay',), ('plan',)
BOTH = SOLVE + REPLAY

SETTINGS = (
    Setting('link_frame', 'tool0',
            'Frame of the robot link that carries the sensor (eye_in_hand) or of the robot '
            'base (eye_to_hand): the parent frame of the result, header.frame_id of '
            '~/rotation. Left at its default with eye_to_hand it is link_frame_id, or '
            'base_link. With TF input, left at its default it is robot_effector_frame '
            '(eye_in_hand) or robot_base_frame (eye_to_hand); set, it must be that frame.'),
    Setting('sensor_frame', 'camera',
            'Frame of the sensor: the child frame of the result. With TF input, left at its '
            'default it is tracking_base_frame; set, it must be that frame.'),
    Setting('robot_base_frame', '',
            'TF input (all four TF frames set): the link pose is robot_base_frame -> '
            'robot_effector_frame, composed from /tf and /tf_static at each stamp, instead '
            "of the link_pose topic. '' (default): the pose topics.", allow_empty=True,
            read_only=True),
    Setting('robot_effector_frame', '',
            'TF input: the robot link the sensor rides on (eye_in_hand) or that holds the '
            "marker (eye_to_hand), e.g. tool0. '' with the other three: the pose topics.",
            allow_empty=True, read_only=True),
    Setting('tracking_base_frame', '',
            'TF input: the sensor pose is tracking_base_frame -> tracking_marker_frame (the '
            "object seen by the sensor), e.g. camera_color_optical_frame -> marker. '' with "
            'the other three: the pose topics.', allow_empty=True, read_only=True),
    Setting('tracking_marker_frame', '',
            "TF input: the observed object's frame (the marker or the board). '' with the "
            'other three: the pose topics.', allow_empty=True, read_only=True),
    Setting('pose_type', 'pose',
            'Message type of link_pose and sensor_pose: pose = geometry_msgs/PoseStamped, '
            'transform = geometry_msgs/TransformStamped, pose_with_covariance = '
            "geometry_msgs/PoseWithCovarianceStamped (the sensor's covariances weight its "
            'samples).', choices=POSE_TYPES, read_only=True),
    Setting('sensor_pose_type', '',
            "Message type of sensor_pose when it differs from link_pose's (one of pose_type's "
            "choices), e.g. pose_with_covariance for the target_detector's poses beside a "
            "robot's PoseStamped; '' = pose_type.", choices=('',) + POSE_TYPES,
            allow_empty=True, read_only=True),
    Setting('sensor_input', 'pose',
            'pose: the sensor pose comes from sensor_pose (or the tracking TF frames); '
            'image: from camera images on image (sensor_msgs/Image) with camera_info, the '
            'board of board_file detected in each (as target_detector does), and the published '
            'estimate is refined on the corners of the samples (method reprojection).',
            choices=SENSOR_INPUTS, read_only=True),
    Setting('board_file', '',
            "The calibration board's board.yaml (type, squares or markers, lengths in metres, "
            "dictionary): required with sensor_input image and for a replay's image topic.",
            allow_empty=True, read_only=True, tools=REPLAY),
    Setting('image_transport', 'raw',
            'With sensor_input image: raw = sensor_msgs/Image on image; compressed = '
            'sensor_msgs/CompressedImage on image/compressed.', choices=IMAGE_TRANSPORTS,
            read_only=True),
    Setting('setup', 'eye_in_hand',
            'eye_in_hand: the sensor rides on the link, the answer is link -> sensor; '
            'eye_to_hand: the sensor is fixed in the cell, the answer is base -> sensor.',
            choices=SETUPS, tools=BOTH + PLAN),
    Setting('capture_mode', 'auto',
            'auto: take a sample whenever both poses stay still for still_window_s after a '
            'motion; manual (the node only): only on ~/capture; continuous: for runs without '
            'stops, a sample each time the link has turned by continuous_step_deg (default '
            'min_motion_deg).',
            choices=CAPTURE_MODES, tools=REPLAY),
    Setting('still_window_s', 0.5,
            'Seconds (header stamps) both poses must stay within the still bands for a '
            'sample.', unit='s', low=0.05, high=10.0, tools=REPLAY),
    Setting('still_rotation_deg', 0.2,
            'Largest link rotation (degrees) within the still window that still counts as '
            'still.', unit='deg', low=0.001, high=5.0, tools=REPLAY),
    Setting('still_translation_m', 0.001,
            'Largest link translation (metres) within the still window that counts as still.',
            unit='m', low=1e-6, high=0.1, tools=REPLAY),
    Setting('sensor_still_rotation_deg', 1.0,
            'Largest sensor-pose rotation (degrees) from the newest within the still window '
            'that counts as still (detections are noisier than the robot). The oldest frame '
            'must be within it, a quarter of the others may pass it (noise, averaged), and '
            'those beyond twice it are left out (a marker flip).', unit='deg', low=0.001,
            high=30.0, tools=REPLAY),
    Setting('sensor_still_translation_m', 0.005,
            'Largest sensor-pose translation (metres) from the newest within the still '
            'window that counts as still, as sensor_still_rotation_deg.', unit='m', low=1e-6,
            high=1.0, tools=REPLAY),
    Setting('min_still_pairs', 3,
            'Fewest paired poses a still window must hold for a sample.', low=1, high=10000,
            tools=REPLAY),
    Setting('min_motion_deg', 5.0,
            'Motions between samples that rotate the link less than this (degrees) carry too '
            'little information: they do not count toward the motions an estimate needs, and '
            'with pairs consecutive they are not used; with pairs all the least squares sums '
            'over every pair of samples, where small motions weigh little.', unit='deg',
            low=0.5, high=90.0,
            tools=BOTH),
    Setting('continuous_step_deg', 0.0,
            'Link rotation (degrees) between two samples in continuous capture; 0: '
            'min_motion_deg.', unit='deg', low=0.0, high=90.0, tools=REPLAY),
    Setting('pairing_tolerance_s', 0.001,
            'Without poses on both sides to interpolate between, a pose this close (seconds, '
            'header stamps) to a stamp of the other stream is paired as it is.', unit='s',
            low=0.0, high=1.0, tools=REPLAY),
    Setting('max_gap_s', 0.1,
            'Largest gap (seconds, header stamps) of a stream across which poses are '
            'interpolated; nothing is paired across a longer gap.', unit='s', low=0.001,
            high=10.0, tools=REPLAY),
    Setting('sensor_time_offset_s', 0.0,
            'Seconds added to every sensor_pose header stamp: a known latency of the sensor '
            'clock, e.g. -0.03 for a camera that stamps its frames 30 ms late (`replay '
            '--estimate-time-offset` measures it from a recording), or the offset of a sensor '
            'computer whose clock is not synchronised.', unit='s', low=-10.0, high=10.0,
            tools=REPLAY),
    Setting('max_stamp_offset_s', 30.0,
            'Pose messages whose header stamp is farther than this (seconds) from the node '
            'clock (with use_sim_time: /clock) are skipped and counted; 0 turns the check '
            'off.', unit='s', low=0.0, high=1e6),
    Setting('max_position_m', 1000.0,
            'Pose messages with a position coordinate farther than this (metres) from the '
            'origin are skipped and counted (implausible_position): a unit error, not a cell.',
            unit='m', low=1.0, high=1e6, tools=REPLAY),
    Setting('link_frame_id', '',
            'header.frame_id that link_pose messages must carry (the robot base frame); '
            "others are skipped and counted. '' accepts any.", allow_empty=True, tools=REPLAY),
    Setting('sensor_frame_id', '',
            "header.frame_id that sensor_pose messages must carry (the sensor's frame); others "
            "are skipped and counted. '' accepts any.", allow_empty=True, tools=REPLAY),
    Setting('pairs', 'all',
            'Motions from all pairs of samples (more information) or consecutive ones only.',
            choices=PAIRS, tools=BOTH),
    Setting('robust', True,
            'Reject bad detections (marker flips) by a consensus search and a heavy-tailed '
            'noise model that down-weights noisy samples; false for plain (weighted) least '
            'squares in every estimate.', tools=BOTH),
    Setting('invert_sensor', False,
            'true: the sensor poses are the sensor in the object frame (the inverse of the '
            'usual detector output). Not with camera images (always the board in the camera '
            'frame).', tools=BOTH),
    Setting('method', 'refined',
            'refined: joint maximum-likelihood refinement over rotations and translations '
            '(from 6 samples on); closed-form: the Chou-Kamel rotation and the closed-form '
            'translation. Both are reported.', choices=METHODS, tools=BOTH),
    Setting('plan_max_rotation_deg', 45.0,
            "The next-pose planner turns the link at most this far from the last sample's "
            'orientation.', unit='deg', low=1.0, high=180.0, tools=BOTH + PLAN),
    Setting('plan_view_cone_deg', 20.0,
            "The next-pose planner keeps the target within this angle of the sensor's "
            'optical axis (z).', unit='deg', low=1.0, high=80.0, tools=BOTH + PLAN),
    Setting('plan_workspace_margin_m', 0.1,
            'The next-pose planner keeps the link inside the box of the link positions seen, '
            'grown by this much on every side.', unit='m', low=0.0, high=10.0, tools=BOTH),
    Setting('known_translation', '',
            'For robots that cannot turn the link freely (a SCARA turns it about one axis, a '
            'gantry not at all), the data leave the translation along that axis (a gantry: '
            "all of it) undetermined: its value, 'x y z' in metres in the result's parent "
            "frame (only the undetermined part is used). '' = zero there, with a warning.",
            allow_empty=True, tools=BOTH),
    Setting('validation_max_rotation_deg', 1.0,
            'The validation passes when the leave-one-out prediction error of the sensor '
            'poses (RMS over the good samples) is at most this angle and '
            'validation_max_translation_mm.', unit='deg', low=0.0, high=180.0, tools=BOTH),
    Setting('validation_max_translation_mm', 10.0,
            'The validation passes when the leave-one-out prediction error of the sensor '
            'positions (RMS over the good samples) is at most this distance and the angle '
            'is within validation_max_rotation_deg.', unit='mm', low=0.0, high=1e6,
            tools=BOTH),
    Setting('result_file', DEFAULT_RESULT_FILE,
            'Where ~/save writes the result YAML (~ is expanded; written atomically). A '
            'path of its own: not samples_file nor easy_handeye2_file; a file in a folder that '
            'can be written (checked at start and when set).'),
    Setting('easy_handeye2_file', '',
            "~/save also writes the result here in easy_handeye2's calibration layout "
            '(parameters + transform; ~ is expanded; written atomically), e.g. '
            "~/.ros2/easy_handeye2/calibrations/NAME.calib. '' does not write it.",
            allow_empty=True),
    Setting('publish_tf', False,
            'true: broadcast the result (link_frame -> sensor_frame) on /tf_static after '
            'every estimate (tf2_msgs/TFMessage, latched). With TF input it never gives a '
            'frame a second parent: where sensor_frame already has a parent, it broadcasts '
            'link_frame -> the root of its static subtree instead. The result is on '
            '~/transform either way.'),
    Setting('samples_file', DEFAULT_SAMPLES_FILE,
            'Journal of the captured samples (samples CSV with a header comment; ~ is '
            "expanded): each sample is appended and fsync'd as it is captured, ~/reset starts "
            'a new one, and the old one is moved aside with a timestamp, never deleted.',
            read_only=True),
    Setting('resume', False,
            'true: continue the session in samples_file (reload its samples and '
            're-estimate); false: move an existing samples_file aside with a timestamp and '
            'start afresh.', read_only=True),
    Setting('diagnostics_period_s', 1.0,
            'Period (seconds, node clock) of the status published on /diagnostics.',
            unit='s', low=0.1, high=60.0, read_only=True),
)
SETTING_BY_NAME = {setting.name: setting for setting in SETTINGS}
DEFAULTS = {setting.name: setting.default for setting in SETTINGS}
# Settings that change only the presentation or the message checks: the node keeps its
# session (and estimate) when only these change.
PRESENTATION = ('link_frame', 'sensor_frame', 'result_file', 'max_stamp_offset_s',
                'max_position_m', 'link_frame_id', 'sensor_frame_id', 'easy_handeye2_file',
                'publish_tf', 'plan_max_rotation_deg', 'plan_view_cone_deg',
                'plan_workspace_margin_m')
# Settings that change only how samples are taken: the node keeps its samples and estimate
# (Session.set_capture).
CAPTURE = ('capture_mode', 'still_window_s', 'still_rotation_deg', 'still_translation_m',
           'sensor_still_rotation_deg', 'sensor_still_translation_m', 'min_still_pairs',
           'continuous_step_deg')


def _from_values(values):
    """
    Check a {name: value} mapping (every setting) and return the Settings.

    :raises ConfigError: naming each value that is not allowed and why, or the core's
        objection to the combination.
    """
    reasons = []
    for setting in SETTINGS:
        if setting.name not in values:
            reasons.append(f'{setting.name} is missing')
            continue
        reason = setting.check(values[setting.name])
        if reason:
            reasons.append(f'parameter {setting.name} {reason}')
    unknown = sorted(set(values) - set(SETTING_BY_NAME))
    if unknown:
        reasons.append(f'unknown setting(s) {", ".join(unknown)}')
    if reasons:
        raise ConfigError('; '.join(reasons))
    settings = Settings(**{s.name: s.plain(values[s.name]) for s in SETTINGS})
    if settings.sensor_input == 'image' and not settings.board_file:
        raise ConfigError('sensor_input image needs board_file: the board.yaml of the target')
    if settings.sensor_input == 'image' and settings.invert_sensor:
        raise ConfigError(IMAGES_NOT_INVERTED)
    known_translation(settings.known_translation)
    _check_result_frames(settings)
    _check_files(settings)
    session_config(settings)   # the core's own consistency checks
    return settings


FILES = ('samples_file', 'result_file', 'easy_handeye2_file')


def _check_files(settings):
    """
    Raise ConfigError when two of the node's files are one, or one is a directory.

    Paths are compared with ~ expanded and links followed. ~/save with result_file at the
    journal's path had replaced the samples with the result.
    """
    seen = {}
    for name in FILES:
        path = getattr(settings, name)
        if not path:
            continue
        target = os.path.realpath(os.path.expanduser(path))
        if os.path.isdir(target):   # (it was found only by ~/save)
            raise ConfigError(f'{name} {path!r} is a directory: give the path of a file in it')
        if target in seen:
            raise ConfigError(f'{seen[target]} and {name} are one file, {path!r}: ~/save '
                              'would replace the one with the other; give each its own path')
        seen[target] = name


def check_writable(settings, names=FILES):
    """
    Raise ConfigError when one of the node's files `names` lies in a folder it cannot write.

    The node's check, at start and when set (a read-only folder was found only by ~/save);
    not the offline tools', which write none of them. A folder still to be made is judged by
    its nearest existing parent.
    """
    for name in names:
        path = getattr(settings, name)
        if not path:
            continue
        folder = _existing_folder(os.path.realpath(os.path.expanduser(path)))
        if not os.access(folder, os.W_OK):
            raise ConfigError(f'{name} {path!r} cannot be written: {folder} is not writable '
                              '(read-only, or not yours): give a path in a writable folder')


def _existing_folder(path):
    """Return the folder of `path` that exists, or its nearest existing ancestor (made later)."""
    folder = os.path.dirname(path)
    while not os.path.isdir(folder) and os.path.dirname(folder) != folder:
        folder = os.path.dirname(folder)
    return folder


def _as_dict(self):
    """Return {name: value} of every setting."""
    return asdict(self)


def _result_frames(self):
    """
    Return the result's (parent, child) frames: link_frame and sensor_frame.

    With TF input, those left at their defaults are the TF frames they stand for (DESIGN.md
    contract 4b): robot_effector_frame (eye_in_hand) or robot_base_frame (eye_to_hand), and
    tracking_base_frame. Without, link_frame left at its default (a flange's name) names the
    robot base with eye_to_hand: link_frame_id, or base_link (units.DEFAULT_FRAMES).
    """
    return tuple(frame for frame, _ in _result_frames_and_origins(self))


def _result_frame_origins(self):
    """
    Return {name: why its frame is not the value given} of the result frames.

    For messages that quote result_frames: a value equal to the default counts as unset.
    """
    return {name: origin for (_, origin), name in
            zip(_result_frames_and_origins(self), ('link_frame', 'sensor_frame')) if origin}


def _result_frames_and_origins(self):
    """Yield (frame, '' or why it is not the value given) of link_frame and sensor_frame."""
    for name, frame, tf_name, tf_frame in _result_frame_sources(self):
        left = f'{name} left at its default {frame!r}'
        if frame == DEFAULTS[name] and tf_frame:
            yield tf_frame, f'as, with TF input, {left} is the TF frame {tf_name}'
        elif frame == DEFAULTS[name] and name == 'link_frame' and self.setup == 'eye_to_hand':
            base = DEFAULT_FRAMES['eye_to_hand'][0]
            yield (self.link_frame_id or base,
                   f'as, with eye_to_hand, {left} names the robot base: link_frame_id, or '
                   f'{base!r}')
        else:
            yield frame, ''


def _result_frame_sources(settings):
    """Yield (name, value, TF setting's name, its value or '') of link_frame and sensor_frame."""
    parent = 'robot_effector_frame' if settings.setup == 'eye_in_hand' else 'robot_base_frame'
    for name, tf_name in (('link_frame', parent), ('sensor_frame', 'tracking_base_frame')):
        yield name, getattr(settings, name), tf_name, getattr(settings, tf_name)


def _check_result_frames(settings):
    """
    Raise ConfigError when link_frame or sensor_frame, set, contradict the TF frames.

    Or when the result's two frames are one (tf2 refuses a transform from a frame to itself).
    """
    for name, frame, tf_name, tf_frame in _result_frame_sources(settings):
        if tf_frame and frame not in (DEFAULTS[name], tf_frame):
            raise ConfigError(f'{name} {frame!r} contradicts {tf_name} {tf_frame!r}: with TF '
                              f'input the result is named by the TF frames; leave {name} '
                              f'unset or set it to {tf_frame!r}')
    parent, child = settings.result_frames
    for frame, which in ((parent, 'parent (link_frame; eye_to_hand: the robot base)'),
                         (child, 'child (sensor_frame)')):
        problem = frame_problem(frame)
        if problem:
            raise ConfigError(f"the result's {which}: {problem}")
    if normalize_frame(parent) == normalize_frame(child):
        raise ConfigError(f'the result would be a transform from frame {child!r} to itself: '
                          'its parent (link_frame; eye_to_hand: the robot base) and its child '
                          '(sensor_frame) must be different frames')


def _updated(self, **changes):
    """Return these settings with `changes` applied, checked; ConfigError when refused."""
    return _from_values({**asdict(self), **changes})


Settings = make_dataclass(
    'Settings', [(s.name, type(s.default), field(default=s.default)) for s in SETTINGS],
    frozen=True, namespace={
        '__doc__': 'One checked value per setting of SETTINGS (plain Python types).',
        '__module__': __name__,
        'from_values': staticmethod(_from_values),
        'as_dict': _as_dict,
        'updated': _updated,
        'result_frames': property(_result_frames),
        'result_frame_origins': property(_result_frame_origins),
    })


def session_config(settings, images=False):
    """
    Return the core's SessionConfig for `settings` (durations in integer ns).

    images: the sensor poses are board poses from camera images (as with sensor_input image),
    which are never inverted.

    min_motion_deg is the calibration's smallest usable motion and, unless
    continuous_step_deg is set, the step of continuous capture.  An automatic still capture
    needs the link to depart at least twice the still bands (and CaptureConfig's own minimum)
    from the previous sample; the pairing keeps at least two gaps of each stream; a manual
    capture needs a pair from the last two still windows.
    :raises ConfigError: when the core refuses the combination.
    """
    default_capture, default_pairing = CaptureConfig(), PairingConfig()
    max_gap_ns = ns_from_s(settings.max_gap_s)
    try:
        return SessionConfig(
            pairing=PairingConfig(
                tolerance_ns=ns_from_s(settings.pairing_tolerance_s), max_gap_ns=max_gap_ns,
                window_ns=max(default_pairing.window_ns, 2 * max_gap_ns)),
            capture=CaptureConfig(
                mode=settings.capture_mode, window_ns=ns_from_s(settings.still_window_s),
                rotation_band_deg=settings.still_rotation_deg,
                translation_band_m=settings.still_translation_m,
                sensor_rotation_band_deg=settings.sensor_still_rotation_deg,
                sensor_translation_band_m=settings.sensor_still_translation_m,
                min_departure_deg=max(default_capture.min_departure_deg,
                                      2.0 * settings.still_rotation_deg),
                min_departure_m=max(default_capture.min_departure_m,
                                    2.0 * settings.still_translation_m),
                min_still_pairs=settings.min_still_pairs,
                recent_ns=max(default_capture.recent_ns,
                              2 * ns_from_s(settings.still_window_s)),
                continuous_step_deg=settings.continuous_step_deg or settings.min_motion_deg),
            calibration=CalibrationOptions(
                setup=settings.setup, pairs=settings.pairs, robust=settings.robust,
                invert_sensor=settings.invert_sensor, min_motion_deg=settings.min_motion_deg,
                sensor_invertible=not (images or settings.sensor_input == 'image'),
                method=settings.method, validation=Thresholds(
                    settings.validation_max_rotation_deg,
                    settings.validation_max_translation_mm),
                known_translation=known_translation(settings.known_translation)),
            sensor_offset_ns=ns_from_s(settings.sensor_time_offset_s))
    except ValueError as error:
        raise ConfigError(f'inconsistent settings: {error}') from None


def known_translation(text):
    """Return the known_translation setting's (x, y, z) in metres, or None for ''."""
    if not text.strip():
        return None
    try:
        values = tuple(plain_number(v) for v in text.replace(',', ' ').split())
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise ConfigError(f"known_translation must be three numbers 'x y z' in metres, not "
                          f'{text!r}')
    problem = position_problem(values)
    if problem:
        raise ConfigError(f'known_translation {text!r}: {problem}')
    return values


TF_FRAMES = ('robot_base_frame', 'robot_effector_frame', 'tracking_base_frame',
             'tracking_marker_frame')


def tf_frames(settings):
    """
    Return {LINK: (base, effector), SENSOR: (tracking base, marker)}, or None (topics).

    With sensor_input image only the link comes from TF: {LINK: (base, effector)}.

    :raises ConfigError: when some of the four TF frames are set and others not.
    """
    values = [getattr(settings, name) for name in TF_FRAMES]
    if not any(values):
        return None
    if settings.sensor_input == 'image':   # the sensor pose comes from the images
        if any(values[2:]):
            raise ConfigError('with sensor_input image the sensor pose comes from the images: '
                              "leave tracking_base_frame and tracking_marker_frame ''")
        names, values = TF_FRAMES[:2], values[:2]
    else:
        names = TF_FRAMES
    missing = [name for name, value in zip(names, values) if not value]
    if missing:
        images = (' (with camera images, sensor_input:=image, the two robot frames alone)'
                  if len(names) == 4 and missing == list(TF_FRAMES[2:]) else '')
        raise ConfigError(f'TF input needs {"both" if len(names) == 2 else "all four"} frames: '
                          f'{", ".join(missing)} not set{images}')
    frames = {LINK: tuple(values[:2])}
    if len(values) == 4:
        frames[SENSOR] = tuple(values[2:])
    return frames


def easy_handeye2_frames(settings):
    """
    Return the frames of easy_handeye2's file beside the result's, those the settings name.

    {robot_base_frame, robot_effector_frame, tracking_marker_frame: name}: the TF frames when
    set, and the robot base the link poses' header names (link_frame_id, eye_in_hand).
    """
    frames = {name: getattr(settings, name) for name in
              ('robot_base_frame', 'robot_effector_frame', 'tracking_marker_frame')}
    if settings.setup == 'eye_in_hand' and not frames['robot_base_frame']:
        frames['robot_base_frame'] = settings.link_frame_id
    return {name: frame for name, frame in frames.items() if frame}


def check_config(settings):
    """Return the message_checks.CheckConfig of `settings` (what pose messages must satisfy)."""
    return CheckConfig(max_stamp_offset_ns=ns_from_s(settings.max_stamp_offset_s),
                       link_frame_id=settings.link_frame_id,
                       sensor_frame_id=settings.sensor_frame_id,
                       max_position_m=settings.max_position_m)


def pose_types(settings):
    """Return {LINK: pose_type, SENSOR: sensor_pose_type or pose_type}: each topic's type."""
    return {LINK: settings.pose_type, SENSOR: settings.sensor_pose_type or settings.pose_type}


def plan_limits(settings):
    """Return the next-pose planner's core.planner.PlanLimits of the settings."""
    return PlanLimits(max_rotation_deg=settings.plan_max_rotation_deg,
                      cone_deg=settings.plan_view_cone_deg,
                      margin_m=settings.plan_workspace_margin_m)
