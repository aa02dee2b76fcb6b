"""Tests of quatcal_ros.ros.node_config: declarations, checks, and the frozen config."""

from dataclasses import fields
import math

import pytest
from quatcal_ros.ros import node_config
from quatcal_ros.ros.node_config import ConfigError, NodeConfig, SPECS
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
import yaml

DEFAULTS = NodeConfig().as_dict()


@pytest.fixture
def context(domain_id):
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _declared(context, overrides=()):
    node = Node('calibrator', context=context, parameter_overrides=list(overrides))
    try:
        return node_config.declare_parameters(node), node
    except ConfigError:
        node.destroy_node()
        raise


def test_specs_match_the_config_fields_and_defaults():
    assert [spec.name for spec in SPECS] == [f.name for f in fields(NodeConfig)]
    for spec in SPECS:
        assert DEFAULTS[spec.name] == spec.default, spec.name
        assert spec.check(spec.default) is None, spec.name
    assert 'use_sim_time' not in DEFAULTS


def test_descriptors_have_descriptions_ranges_and_read_only():
    for spec in SPECS:
        descriptor = spec.descriptor()
        assert descriptor.name == spec.name
        assert len(descriptor.description) > 20, spec.name
        if isinstance(spec.default, float):
            (limits,) = descriptor.floating_point_range
            assert limits.from_value <= spec.default <= limits.to_value
        if spec.choices:
            assert all(choice in descriptor.additional_constraints for choice in spec.choices)
    read_only = {spec.name for spec in SPECS if spec.descriptor().read_only}
    assert read_only == {'pose_type', 'diagnostics_period_s', 'samples_file', 'resume'}


def test_session_config_gets_plain_numbers_in_nanoseconds():
    config = NodeConfig.from_values(dict(
        DEFAULTS, still_window_s=0.25, max_gap_s=0.05, pairing_tolerance_s=0.002,
        setup='eye_to_hand', pairs='consecutive', robust=False, capture_mode='manual',
        min_motion_deg=8.0))
    session = node_config.session_config(config)
    assert session.capture.window_ns == 250_000_000
    assert isinstance(session.capture.window_ns, int)
    assert session.capture.mode == 'manual'
    assert session.capture.rotation_band_deg == config.still_rotation_deg
    assert session.capture.continuous_step_deg == 8.0
    assert session.pairing.max_gap_ns == 50_000_000
    assert session.pairing.tolerance_ns == 2_000_000
    assert session.calibration.setup == 'eye_to_hand'
    assert session.calibration.pairs == 'consecutive'
    assert session.calibration.robust is False
    assert session.calibration.min_motion_deg == 8.0


@pytest.mark.parametrize('name, value, words', [
    ('setup', 'sideways', 'eye_in_hand'),
    ('pose_type', 'odometry', 'transform'),
    ('capture_mode', 'sometimes', 'continuous'),
    ('pairs', 'some', 'consecutive'),
    ('still_window_s', -1.0, 'between'),
    ('still_window_s', math.nan, 'between'),
    ('max_gap_s', 100.0, 'between'),
    ('sensor_time_offset_s', 2.0, 'between'),
    ('min_motion_deg', 'five', 'number'),
    ('robust', 1, 'true or false'),
    ('link_frame', '', 'empty'),
    ('result_file', '  ', 'empty'),
])
def test_invalid_values_are_refused_with_the_reason(name, value, words):
    with pytest.raises(ConfigError) as error:
        NodeConfig.from_values(dict(DEFAULTS, **{name: value}))
    assert name in str(error.value) and words in str(error.value)


def test_integers_for_floats_become_floats():
    config = NodeConfig.from_values(dict(DEFAULTS, still_window_s=1))
    assert config.still_window_s == 1.0 and isinstance(config.still_window_s, float)


def test_declare_parameters_with_overrides(context):
    config, node = _declared(context, [
        Parameter('setup', value='eye_to_hand'), Parameter('still_window_s', value=0.3),
        Parameter('robust', value=False)])
    try:
        assert config.setup == 'eye_to_hand'
        assert config.still_window_s == 0.3
        assert config.robust is False
        assert config.link_frame == 'tool0'
        assert node.describe_parameter('pose_type').read_only
        assert node.describe_parameter('still_window_s').floating_point_range
        assert node.has_parameter('use_sim_time')
    finally:
        node.destroy_node()


@pytest.mark.parametrize('override, words', [
    (Parameter('still_window_s', value=100.0), 'still_window_s'),
    (Parameter('still_window_s', value=1), 'still_window_s'),     # integer for a double
    (Parameter('setup', value='sideways'), 'setup'),
    (Parameter('robust', value='yes'), 'robust'),
])
def test_declare_refuses_invalid_overrides(context, override, words):
    with pytest.raises(ConfigError, match=words):
        _declared(context, [override])


def test_updated_checks_runtime_changes():
    config = NodeConfig()
    changed = node_config.updated(config, [Parameter('pairs', value='consecutive'),
                                           Parameter('use_sim_time', value=True)])
    assert changed.pairs == 'consecutive' and config.pairs == 'all'
    with pytest.raises(ConfigError, match='min_motion_deg'):
        node_config.updated(config, [Parameter('min_motion_deg', value=0.0)])


def test_params_file_lists_every_parameter_with_its_default(repo_root):
    path = repo_root / 'config' / 'calibrator.yaml'
    text = path.read_text()
    document = yaml.safe_load(text)
    parameters = document['calibrator']['ros__parameters']
    assert parameters == DEFAULTS
    lines = text.splitlines()
    for spec in SPECS:
        (index,) = [i for i, line in enumerate(lines) if line.strip().startswith(spec.name + ':')]
        assert lines[index - 1].strip().startswith('#'), f'{spec.name} has no comment'


def test_params_file_loads_through_rcl(repo_root, domain_id):
    path = repo_root / 'config' / 'calibrator.yaml'
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id,
               args=['calibrator', '--ros-args', '--params-file', str(path)])
    try:
        config, node = _declared(ctx)
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
    assert config == NodeConfig()


def test_sensor_time_offset_reaches_the_session():
    config = NodeConfig.from_values({**DEFAULTS, 'sensor_time_offset_s': -0.03})
    assert node_config.session_config(config).sensor_offset_ns == -30_000_000
