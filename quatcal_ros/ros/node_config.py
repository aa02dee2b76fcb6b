"""
The calibrator node's parameters: declarations, validation, and the frozen config.

Every parameter is declared with a ParameterDescriptor (description, range, read_only).  The
values are checked together (ranges, enumerations, non-empty names) into a frozen
`NodeConfig` of plain Python numbers and strings; `session_config()` turns it into the core's
`session.SessionConfig`.  The same checks run at startup (`declare_parameters`, which raises
`ConfigError` with the reason) and at runtime (`updated`, used by the node's set-parameters
callback).  `use_sim_time` is rclpy's own and is not declared here.
"""

from dataclasses import asdict, dataclass, fields
import math

from quatcal_ros.core.calibration import CalibrationOptions
from quatcal_ros.core.units import ns_from_s, SETUPS
from quatcal_ros.stream.message_checks import CheckConfig
from quatcal_ros.stream.session import session_config_from_settings
from rcl_interfaces.msg import FloatingPointRange
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException

DEFAULT_RESULT_FILE = '~/.ros/quatcal/calibration.yaml'
DEFAULT_SAMPLES_FILE = '~/.ros/quatcal/samples.csv'
POSE_TYPES = ('pose', 'transform')
CAPTURE_MODES = ('auto', 'manual', 'continuous')
PAIRS = ('all', 'consecutive')


class ConfigError(ValueError):
    """A parameter value the node cannot work with; the message names it and says why."""


@dataclass(frozen=True)
class Spec:
    """One parameter: default, description, and its allowed values."""

    name: str
    default: object
    description: str
    choices: tuple = ()
    low: float = None
    high: float = None
    read_only: bool = False
    allow_empty: bool = False

    def descriptor(self):
        """Return the ParameterDescriptor declared with the parameter."""
        constraints = ''
        if self.choices:
            constraints = 'one of: ' + ', '.join(self.choices)
        elif self.low is not None:
            constraints = f'{self.low:g} to {self.high:g}'
        descriptor = ParameterDescriptor(
            name=self.name, description=self.description,
            additional_constraints=constraints, read_only=self.read_only)
        if self.low is not None:
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(self.low), to_value=float(self.high),
                                   step=0.0)]
        return descriptor

    def check(self, value):
        """Why `value` is not allowed, or None when it is."""
        if isinstance(self.default, bool):
            return None if isinstance(value, bool) else f'must be true or false, not {value!r}'
        if isinstance(self.default, float):
            return self._check_number(value)
        if not isinstance(value, str):
            return f'must be a string, not {value!r}'
        if self.choices and value not in self.choices:
            return f'must be one of {", ".join(self.choices)}, not {value!r}'
        if not value.strip() and not (self.allow_empty and value == ''):
            return 'must not be empty' + (" (or '' for any)" if self.allow_empty else '')
        return None

    def _check_number(self, value):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            return f'must be a number, not {value!r}'
        if not math.isfinite(value) or not self.low <= value <= self.high:
            return f'must be between {self.low:g} and {self.high:g}, not {value!r}'
        return None


SPECS = (
    Spec('link_frame', 'tool0',
         'Frame of the robot link that carries the sensor (eye_in_hand) or of the robot base '
         '(eye_to_hand): the parent frame of the result, header.frame_id of ~/rotation.'),
    Spec('sensor_frame', 'camera', 'Frame of the sensor: the child frame of the result.'),
    Spec('pose_type', 'pose',
         'Message type of link_pose and sensor_pose: pose = geometry_msgs/PoseStamped, '
         'transform = geometry_msgs/TransformStamped.', choices=POSE_TYPES, read_only=True),
    Spec('setup', 'eye_in_hand',
         'eye_in_hand: the sensor rides on the link, the answer is link -> sensor; '
         'eye_to_hand: the sensor is fixed in the cell, the answer is base -> sensor.',
         choices=SETUPS),
    Spec('capture_mode', 'auto',
         'auto: take a sample whenever both poses stay still for still_window_s after a '
         'motion; manual: only on ~/capture; continuous: for runs without stops, a sample '
         'each time the link has turned by min_motion_deg.', choices=CAPTURE_MODES),
    Spec('still_window_s', 0.5,
         'Seconds (header stamps) both poses must stay within the still bands for a sample.',
         low=0.05, high=10.0),
    Spec('still_rotation_deg', 0.2,
         'Largest link rotation (degrees) within the still window that still counts as still.',
         low=0.001, high=5.0),
    Spec('still_translation_m', 0.001,
         'Largest link translation (metres) within the still window that counts as still.',
         low=1e-6, high=0.1),
    Spec('min_motion_deg', 5.0,
         'Motions between samples that rotate the link less than this (degrees) carry too '
         'little information and are not used.', low=0.5, high=90.0),
    Spec('pairing_tolerance_s', 0.001,
         'Without poses on both sides to interpolate between, a pose this close (seconds, '
         'header stamps) to a stamp of the other stream is paired as it is.', low=0.0,
         high=1.0),
    Spec('max_gap_s', 0.1,
         'Largest gap (seconds, header stamps) of a stream across which poses are '
         'interpolated; nothing is paired across a longer gap.', low=0.001, high=10.0),
    Spec('sensor_time_offset_s', 0.0,
         'Seconds added to every sensor_pose header stamp: a known latency of the sensor '
         'clock, e.g. -0.03 for a camera that stamps its frames 30 ms late (`replay '
         '--estimate-time-offset` measures it from a recording).', low=-1.0, high=1.0),
    Spec('max_stamp_offset_s', 30.0,
         'Pose messages whose header stamp is farther than this (seconds) from the node clock '
         '(with use_sim_time: /clock) are skipped and counted; 0 turns the check off.',
         low=0.0, high=1e6),
    Spec('link_frame_id', '',
         'header.frame_id that link_pose messages must carry (the robot base frame); others '
         "are skipped and counted. '' accepts any.", allow_empty=True),
    Spec('sensor_frame_id', '',
         "header.frame_id that sensor_pose messages must carry (the sensor's frame); others "
         "are skipped and counted. '' accepts any.", allow_empty=True),
    Spec('pairs', 'all',
         'Motions from all pairs of samples (more information) or consecutive ones only.',
         choices=PAIRS),
    Spec('robust', True,
         'Reject bad detections (marker flips) and inconsistent motions by a consensus '
         'search; false for plain least squares.'),
    Spec('result_file', DEFAULT_RESULT_FILE,
         'Where ~/save writes the result YAML (~ is expanded; written atomically).'),
    Spec('easy_handeye2_file', '',
         "~/save also writes the result here in easy_handeye2's calibration layout "
         '(parameters + transform; ~ is expanded; written atomically), e.g. '
         "~/.ros2/easy_handeye2/calibrations/NAME.calib. '' does not write it.",
         allow_empty=True),
    Spec('publish_tf', False,
         'true: broadcast the result (link_frame -> sensor_frame) on /tf_static after every '
         'estimate, with tf2_ros (a ROS 2 install); without tf2_ros the node warns and '
         'reports it in /diagnostics. The result is on ~/transform either way.'),
    Spec('samples_file', DEFAULT_SAMPLES_FILE,
         'Journal of the captured samples (samples CSV with a header comment; ~ is expanded): '
         "each sample is appended and fsync'd as it is captured, ~/reset starts a new one, "
         'and the old one is moved aside with a timestamp, never deleted.', read_only=True),
    Spec('resume', False,
         'true: continue the session in samples_file (reload its samples and re-estimate); '
         'false: move an existing samples_file aside with a timestamp and start afresh.',
         read_only=True),
    Spec('diagnostics_period_s', 1.0,
         'Period (seconds, node clock) of the status published on /diagnostics.',
         low=0.1, high=60.0, read_only=True),
)
SPEC_BY_NAME = {spec.name: spec for spec in SPECS}


@dataclass(frozen=True)
class NodeConfig:
    """The node's checked parameter values (plain Python types)."""

    link_frame: str = 'tool0'
    sensor_frame: str = 'camera'
    pose_type: str = 'pose'
    setup: str = 'eye_in_hand'
    capture_mode: str = 'auto'
    still_window_s: float = 0.5
    still_rotation_deg: float = 0.2
    still_translation_m: float = 0.001
    min_motion_deg: float = 5.0
    pairing_tolerance_s: float = 0.001
    max_gap_s: float = 0.1
    sensor_time_offset_s: float = 0.0
    max_stamp_offset_s: float = 30.0
    link_frame_id: str = ''
    sensor_frame_id: str = ''
    pairs: str = 'all'
    robust: bool = True
    result_file: str = DEFAULT_RESULT_FILE
    easy_handeye2_file: str = ''
    publish_tf: bool = False
    samples_file: str = DEFAULT_SAMPLES_FILE
    resume: bool = False
    diagnostics_period_s: float = 1.0

    @staticmethod
    def from_values(values):
        """Check a {name: value} mapping (all parameters) and freeze it; raises ConfigError."""
        reasons = []
        for spec in SPECS:
            reason = spec.check(values.get(spec.name))
            if reason:
                reasons.append(f'parameter {spec.name} {reason}')
        if reasons:
            raise ConfigError('; '.join(reasons))
        config = NodeConfig(**{f.name: _plain(values[f.name]) for f in fields(NodeConfig)})
        session_config(config)   # the core's own consistency checks
        return config

    def as_dict(self):
        """{name: value} of every parameter."""
        return asdict(self)


def _plain(value):
    return float(value) if isinstance(value, int) and not isinstance(value, bool) else value


def declare_parameters(node):
    """
    Declare every parameter on `node` and return the checked NodeConfig.

    :raises ConfigError: with the reason, for a value of the wrong type, out of range, or not
        one of the allowed choices (from parameter_overrides or --ros-args -p).
    """
    for spec in SPECS:
        try:
            node.declare_parameter(spec.name, spec.default, spec.descriptor())
        except ParameterException as error:
            raise ConfigError(f'parameter {spec.name}: {error}') from None
    return NodeConfig.from_values(
        {spec.name: node.get_parameter(spec.name).value for spec in SPECS})


def updated(config, parameters):
    """
    Return the NodeConfig after setting `parameters` (rclpy Parameter objects).

    :raises ConfigError: when a new value is not allowed; `config` stays as it was.
    """
    values = config.as_dict()
    for parameter in parameters:
        if parameter.name in SPEC_BY_NAME:
            values[parameter.name] = parameter.value
    return NodeConfig.from_values(values)


def session_config(config):
    """
    Return the core's session.SessionConfig for `config` (durations in integer ns).

    min_motion_deg is the calibration's smallest usable motion and the step of 'continuous'
    capture; an automatic still capture needs the link to move at least twice the still bands
    (and CaptureConfig's own minimum) away from the previous sample.
    :raises ConfigError: when the core refuses the combination.
    """
    try:
        return session_config_from_settings(
            CalibrationOptions(setup=config.setup, pairs=config.pairs,
                               robust=bool(config.robust), min_motion_deg=config.min_motion_deg),
            capture_mode=config.capture_mode, still_window_s=config.still_window_s,
            still_rotation_deg=config.still_rotation_deg,
            still_translation_m=config.still_translation_m,
            min_motion_deg=config.min_motion_deg, pairing_tolerance_s=config.pairing_tolerance_s,
            max_gap_s=config.max_gap_s, sensor_offset_s=config.sensor_time_offset_s)
    except ValueError as error:
        raise ConfigError(f'inconsistent parameters: {error}') from None


def check_config(config):
    """Return the message_checks.CheckConfig of `config` (what pose messages must satisfy)."""
    return CheckConfig(max_stamp_offset_ns=ns_from_s(config.max_stamp_offset_s),
                       link_frame_id=config.link_frame_id,
                       sensor_frame_id=config.sensor_frame_id)
