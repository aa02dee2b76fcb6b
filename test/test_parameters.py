"""Tests of the settings table (stream.settings) and the node's parameters made from it."""

import argparse
from dataclasses import fields
import importlib
import math

import pytest
from quatcal_ros.ros import parameters
from quatcal_ros.stream import settings
from quatcal_ros.stream.settings import CAPTURE, ConfigError, PRESENTATION, SETTINGS, Settings
from quatcal_ros.tools import options
import rclpy
from rclpy.context import Context
from rclpy.node import Node
from rclpy.parameter import Parameter
import yaml

DEFAULTS = Settings().as_dict()


@pytest.fixture
def context(domain_id):
    ctx = Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    yield ctx
    rclpy.try_shutdown(context=ctx)


def _declared(context, overrides=()):
    node = Node('calibrator', context=context, parameter_overrides=list(overrides))
    try:
        return parameters.declare_parameters(node), node
    except ConfigError:
        node.destroy_node()
        raise


def test_table_rows_are_the_settings_fields_and_defaults():
    assert [setting.name for setting in SETTINGS] == [f.name for f in fields(Settings)]
    for setting in SETTINGS:
        assert DEFAULTS[setting.name] == setting.default, setting.name
        assert type(DEFAULTS[setting.name]) is type(setting.default), setting.name
        assert setting.check(setting.default) is None, setting.name
        assert len(setting.description) > 20, setting.name
    assert 'use_sim_time' not in DEFAULTS


def test_descriptors_have_descriptions_ranges_and_read_only():
    for setting in SETTINGS:
        descriptor = parameters.descriptor(setting)
        assert descriptor.name == setting.name
        assert descriptor.description == setting.description
        if isinstance(setting.default, float):
            (limits,) = descriptor.floating_point_range
            assert limits.from_value <= setting.default <= limits.to_value
        elif isinstance(setting.default, int) and not isinstance(setting.default, bool):
            (limits,) = descriptor.integer_range
            assert limits.from_value <= setting.default <= limits.to_value
        if setting.choices:
            assert all(c in descriptor.additional_constraints for c in setting.choices)
    read_only = {s.name for s in SETTINGS if parameters.descriptor(s).read_only}
    assert read_only == {'pose_type', 'sensor_pose_type', 'diagnostics_period_s', 'samples_file',
                         'resume', 'sensor_input', 'board_file', 'image_transport',
                         'robot_base_frame', 'robot_effector_frame', 'tracking_base_frame',
                         'tracking_marker_frame'}


def test_session_config_gets_plain_numbers_in_nanoseconds():
    config = Settings.from_values(dict(
        DEFAULTS, still_window_s=0.25, max_gap_s=0.05, pairing_tolerance_s=0.002,
        setup='eye_to_hand', pairs='consecutive', robust=False, capture_mode='manual',
        min_motion_deg=8.0))
    session = settings.session_config(config)
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
    ('sensor_time_offset_s', 20.0, 'between'),
    ('min_motion_deg', 'five', 'number'),
    ('robust', 1, 'true or false'),
    ('link_frame', '', 'empty'),
    ('result_file', '  ', 'empty'),
    ('known_translation', '1e9 1e9 1e9', 'not a position in a robot cell'),
    ('known_translation', '0_5 0 0', 'three numbers'),        # float() read 5
    ('known_translation', '\u0663 0 0', 'three numbers'),     # float() read 3
])
def test_invalid_values_are_refused_with_the_reason(name, value, words):
    with pytest.raises(ConfigError) as error:
        Settings.from_values(dict(DEFAULTS, **{name: value}))
    assert name in str(error.value) and words in str(error.value)


def test_two_files_at_one_path_are_refused(tmp_path):
    """result_file at the journal's path: ~/save had replaced the samples with the result."""
    journal = tmp_path / 'samples.csv'
    (tmp_path / 'link.csv').symlink_to(journal)
    for name, path in (('result_file', journal), ('easy_handeye2_file', tmp_path / 'link.csv')):
        with pytest.raises(ConfigError, match=f'samples_file and {name} are one file'):
            Settings.from_values(dict(DEFAULTS, samples_file=str(journal), **{name: str(path)}))
    with pytest.raises(ConfigError, match='result_file and easy_handeye2_file are one file'):
        Settings.from_values(dict(DEFAULTS, result_file='~/r.yaml', easy_handeye2_file='~/r.yaml'))
    apart = Settings.from_values(dict(DEFAULTS, easy_handeye2_file=str(tmp_path / 'a.calib')))
    assert apart.easy_handeye2_file.endswith('a.calib')
    # A directory was accepted at start and at runtime, and failed only at ~/save.
    for name in ('result_file', 'easy_handeye2_file'):
        with pytest.raises(ConfigError, match=f"^{name} '{tmp_path}' is a directory: give the "
                                              'path of a file in it$'):
            Settings.from_values(dict(DEFAULTS, **{name: str(tmp_path)}))


def test_a_file_in_a_folder_that_cannot_be_written_is_refused(tmp_path, monkeypatch):
    """A read-only folder was accepted at start and at runtime, and failed only at ~/save."""
    module, updated = settings, parameters.updated
    locked = tmp_path / 'locked'
    locked.mkdir()
    # (root writes anywhere but on a read-only mount: the check is os.access's)
    monkeypatch.setattr(module.os, 'access', lambda path, mode: path != str(locked))
    for name in ('result_file', 'easy_handeye2_file'):
        for path in (locked / 'r.yaml', locked / 'new' / 'deeper' / 'r.yaml'):
            with pytest.raises(ConfigError) as refused:   # (the node's: at runtime)
                updated(Settings.from_values(DEFAULTS), [Parameter(name, value=str(path))])
            assert str(refused.value) == (
                f"{name} '{path}' cannot be written: {locked} is not writable (read-only, or "
                'not yours): give a path in a writable folder')
            # The offline tools write none of them: nothing to refuse there.
            assert Settings.from_values(dict(DEFAULTS, **{name: str(path)}))
        # a folder still to be made in a writable one: made by ~/save
        assert updated(Settings.from_values(DEFAULTS),
                       [Parameter(name, value=str(tmp_path / 'new' / 'r.yaml'))])
    # A folder that became read-only while the node ran does not block other changes.
    running = Settings.from_values(dict(DEFAULTS, result_file=str(locked / 'r.yaml')))
    assert updated(running, [Parameter('pairs', value='consecutive')]).pairs == 'consecutive'


def test_integers_for_floats_become_floats():
    config = Settings.from_values(dict(DEFAULTS, still_window_s=1))
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
    (Parameter('still_window_s', value=100), 'must be between 0.05 and 10, not 100.0'),  # real
    (Parameter('still_window_s', value='1'), "must be a number, not '1'"),
    (Parameter('setup', value='sideways'), 'setup'),
    (Parameter('robust', value='yes'), 'robust'),
])
def test_declare_refuses_invalid_overrides(context, override, words):
    with pytest.raises(ConfigError, match=words):
        _declared(context, [override])


def test_updated_checks_runtime_changes():
    config = Settings()
    changed = parameters.updated(config, [Parameter('pairs', value='consecutive'),
                                          Parameter('use_sim_time', value=True)])
    assert changed.pairs == 'consecutive' and config.pairs == 'all'
    with pytest.raises(ConfigError, match='min_motion_deg'):
        parameters.updated(config, [Parameter('min_motion_deg', value=0.0)])


def test_params_file_lists_every_parameter_with_its_default(repo_root):
    path = repo_root / 'config' / 'calibrator.yaml'
    text = path.read_text()
    document = yaml.safe_load(text)
    parameters = document['calibrator']['ros__parameters']
    assert parameters == DEFAULTS
    lines = text.splitlines()
    for setting in SETTINGS:
        (index,) = [i for i, line in enumerate(lines)
                    if line.strip().startswith(setting.name + ':')]
        assert lines[index - 1].strip().startswith('#'), f'{setting.name} has no comment'
        # A runtime change of these keeps the estimate (the node keeps its session).
        start = index
        while lines[start - 1].strip().startswith('#'):
            start -= 1
        comment = ' '.join(line.strip().lstrip('# ') for line in lines[start:index])
        assert (('keeps the estimate' in comment)
                == (setting.name in PRESENTATION + CAPTURE)), setting.name


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
    assert config == Settings()


def test_sensor_time_offset_reaches_the_session():
    config = Settings.from_values({**DEFAULTS, 'sensor_time_offset_s': -0.03})
    assert settings.session_config(config).sensor_offset_ns == -30_000_000


def test_params_file_is_the_table(repo_root):
    path = repo_root / 'config' / 'calibrator.yaml'
    assert path.read_text() == parameters.params_file_text(), \
        'config/calibrator.yaml is out of date: python -m quatcal_ros.ros.parameters > ' \
        'config/calibrator.yaml'


def test_unknown_settings_and_choices_are_refused_with_the_choices_named():
    with pytest.raises(ConfigError, match='unknown setting'):
        Settings.from_values(dict(DEFAULTS, still_windows=1.0))
    with pytest.raises(ConfigError, match='refined, closed-form'):
        Settings.from_values(dict(DEFAULTS, method='refine'))


def test_continuous_step_defaults_to_the_smallest_motion():
    config = Settings.from_values(dict(DEFAULTS, min_motion_deg=8.0))
    assert settings.session_config(config).capture.continuous_step_deg == 8.0
    config = config.updated(continuous_step_deg=3.0)
    assert settings.session_config(config).capture.continuous_step_deg == 3.0
    assert settings.session_config(config).calibration.min_motion_deg == 8.0


def _replay_options(argv):
    parser = argparse.ArgumentParser(exit_on_error=False)
    options.add_setting_options(parser, 'replay')
    return parser.parse_args(argv)


def test_command_line_options_are_the_table_rows():
    args = _replay_options([])
    assert options.settings_of(args) == Settings()
    args = _replay_options(['--still-window-s', '0.25', '--no-robust', '--capture',
                            'continuous', '--min-still-pairs', '5', '--sensor-time-offset',
                            '-0.03'])
    chosen = options.settings_of(args)
    assert chosen.still_window_s == 0.25 and chosen.robust is False
    assert chosen.capture_mode == 'continuous' and chosen.min_still_pairs == 5
    assert chosen.sensor_time_offset_s == -0.03


@pytest.mark.parametrize('argv, words', [
    (['--still-window-s', '0.01'], 'between 0.05 and 10'),     # the node's range, offline too
    (['--still-window-s', 'nan'], 'between'),
    (['--max-gap-s', '0_1'], 'not a number'),                   # float() would accept it
    (['--min-still-pairs', '2.5'], 'not a whole number'),
    (['--capture', 'manual'], 'invalid choice'),               # no ~/capture offline
])
def test_command_line_values_out_of_the_table_are_refused(argv, words):
    with pytest.raises(argparse.ArgumentError, match=words):
        _replay_options(argv)


def test_tf_input_with_the_robot_frames_alone_names_the_image_input():
    # The camera-image session sets these two alone: the refusal pointed nowhere.
    from quatcal_ros.stream.settings import tf_frames
    robot = {'robot_base_frame': 'base_link', 'robot_effector_frame': 'tool0'}
    with pytest.raises(ConfigError, match=r'^TF input needs all four frames: '
                                          r'tracking_base_frame, tracking_marker_frame not set '
                                          r'\(with camera images, sensor_input:=image, the two '
                                          r'robot frames alone\)$'):
        tf_frames(Settings.from_values({**DEFAULTS, **robot}))
    with pytest.raises(ConfigError, match='tracking_marker_frame not set$'):
        tf_frames(Settings.from_values({**DEFAULTS, **robot, 'tracking_base_frame': 'cam'}))


def test_with_tf_input_the_result_is_named_by_the_tf_frames():
    tf = {'robot_base_frame': 'base_link', 'robot_effector_frame': 'flange',
          'tracking_base_frame': 'cam_optical', 'tracking_marker_frame': 'marker'}
    assert Settings().result_frames == ('tool0', 'camera')
    # Without TF, eye_to_hand's parent is the robot base, not the flange's default name.
    assert Settings().updated(setup='eye_to_hand').result_frames == ('base_link', 'camera')
    assert Settings().updated(setup='eye_to_hand', link_frame_id='world').result_frames == \
        ('world', 'camera')
    assert Settings().updated(setup='eye_to_hand', link_frame='base').result_frames == \
        ('base', 'camera')
    given = Settings.from_values({**DEFAULTS, **tf})
    assert given.result_frames == ('flange', 'cam_optical')
    assert given.updated(setup='eye_to_hand').result_frames == ('base_link', 'cam_optical')
    same = {'link_frame': 'flange', 'sensor_frame': 'cam_optical'}
    assert Settings.from_values({**DEFAULTS, **tf, **same}).result_frames == \
        ('flange', 'cam_optical')
    with pytest.raises(ConfigError, match="link_frame 'tool1' contradicts "
                                          "robot_effector_frame 'flange'"):
        Settings.from_values({**DEFAULTS, **tf, 'link_frame': 'tool1'})
    with pytest.raises(ConfigError, match="sensor_frame 'cam' contradicts "
                                          "tracking_base_frame 'cam_optical'"):
        Settings.from_values({**DEFAULTS, **tf, 'sensor_frame': 'cam'})
    link_only = {'robot_base_frame': 'base_link', 'robot_effector_frame': 'flange',
                 'sensor_input': 'image', 'board_file': 'board.yaml', 'sensor_frame': 'cam'}
    assert Settings.from_values({**DEFAULTS, **link_only}).result_frames == ('flange', 'cam')


def test_result_frames_not_as_given_say_why():
    # A refusal that quotes the result frames says why one is not the value the user gave
    # (a value equal to the default counts as unset: link_frame:=tool0 with eye_to_hand).
    assert Settings().result_frame_origins == {}
    assert Settings().updated(setup='eye_to_hand', link_frame='base').result_frame_origins == {}
    assert Settings().updated(setup='eye_to_hand').result_frame_origins == {
        'link_frame': "as, with eye_to_hand, link_frame left at its default 'tool0' names the "
                      "robot base: link_frame_id, or 'base_link'"}
    tf = {'robot_base_frame': 'base_link', 'robot_effector_frame': 'flange',
          'tracking_base_frame': 'cam_optical', 'tracking_marker_frame': 'marker'}
    assert Settings.from_values({**DEFAULTS, **tf, 'sensor_frame': 'cam_optical'}) \
        .result_frame_origins == {
            'link_frame': "as, with TF input, link_frame left at its default 'tool0' is the TF "
                          'frame robot_effector_frame'}


@pytest.mark.parametrize('changes', [
    {'link_frame': 'camera'},
    {'sensor_frame': '/tool0'},   # the same frame to tf2
    {'setup': 'eye_to_hand', 'link_frame_id': 'camera'},
])
def test_a_result_from_a_frame_to_itself_is_refused(changes):
    with pytest.raises(ConfigError, match='the result would be a transform from frame .* to '
                                          'itself'):
        Settings.from_values({**DEFAULTS, **changes})
    with pytest.raises(ConfigError, match='to itself'):
        Settings().updated(**changes)


@pytest.mark.parametrize('changes, which, frame', [
    ({'sensor_frame': 'my camera'}, 'child', "'my camera'"),
    ({'link_frame': '/'}, 'parent', "'/'"),
    ({'sensor_frame': 'cam\nera'}, 'child', "'cam\\nera'"),
])
def test_a_result_frame_tf_cannot_take_is_refused_as_the_tools_refuse_it(changes, which, frame):
    # The node took them, into its static_transform_publisher line, URDF joint and files; the
    # offline tools refused them: one check now (tf_tree.frame_problem).
    from quatcal_ros.tools.cli import frames_problem
    with pytest.raises(ConfigError) as raised:
        Settings.from_values({**DEFAULTS, **changes})
    said = f'{frame} is not a frame TF can take (empty, or with a space or a control character)'
    assert str(raised.value).startswith(f"the result's {which}") and said in str(raised.value)
    assert frames_problem(Settings().updated().result_frames) == ''
    assert said in frames_problem((changes.get('link_frame', 'tool0'),
                                   changes.get('sensor_frame', 'camera')))


def test_the_cores_own_defaults_are_the_tables():
    # calibrate(samples), Replay(), print_result() use the configurations' dataclass defaults:
    # they must be what the table makes of its defaults.
    from quatcal_ros.core.planner import PlanLimits
    from quatcal_ros.stream.message_checks import CheckConfig
    from quatcal_ros.stream.session import SessionConfig
    assert settings.session_config(Settings()) == SessionConfig()
    assert settings.check_config(Settings()) == CheckConfig()
    assert settings.plan_limits(Settings()) == PlanLimits()


def test_the_easy_handeye2_file_names_every_frame_the_settings_know():
    tf = Settings().updated(setup='eye_to_hand', robot_base_frame='base_link',
                            robot_effector_frame='tool0', tracking_base_frame='camera',
                            tracking_marker_frame='aruco_marker')
    assert settings.easy_handeye2_frames(tf) == {
        'robot_base_frame': 'base_link', 'robot_effector_frame': 'tool0',
        'tracking_marker_frame': 'aruco_marker'}
    topics = Settings().updated(link_frame_id='world')   # the link poses' header frame
    assert settings.easy_handeye2_frames(topics) == {'robot_base_frame': 'world'}
    assert settings.easy_handeye2_frames(topics.updated(setup='eye_to_hand')) == {}
    assert settings.easy_handeye2_frames(Settings()) == {}


def test_board_poses_from_images_are_never_taken_as_inverted():
    # sensor_input image (the node), or images=True (solve DIR, replay --image-topic): the
    # convention check then leaves out the inverted conventions.
    config = settings.session_config
    assert config(Settings()).calibration.sensor_invertible
    assert not config(Settings(), images=True).calibration.sensor_invertible
    assert not config(Settings(sensor_input='image', board_file='board.yaml')) \
        .calibration.sensor_invertible


@pytest.mark.parametrize('tool', ['sim_cell', 'target_detector'])
def test_the_other_nodes_have_a_help_and_refuse_what_ros_would_silently_ignore(tool, capsys):
    # `sim_cell --help` printed nothing and started the cell.
    module = importlib.import_module(f'quatcal_ros.ros.{tool}')
    assert module.main([tool, '--help']) == 0
    said = capsys.readouterr().out
    assert said.startswith(f'usage: ros2 run quatcal_ros {tool} [--ros-args [-p NAME:=VALUE')
    assert '(True)' not in said and '(False)' not in said   # defaults as YAML writes them
    assert all(f'\n  {name} (' in said for name in module.PARAMETERS)
    assert not rclpy.ok()   # nothing started
    assert module.main([tool, '--seed', '3']) == 2
    assert capsys.readouterr().err.startswith(f'{tool}: error: unexpected argument(s) --seed 3')
    name = next(iter(module.PARAMETERS))
    status, said = module.command_line_problem([tool, f'{name}:=3'])
    assert (status, said) == (2, f'{name}:=3: outside --ros-args, ROS takes NAME:=VALUE for a '
                                 'topic remap, not a parameter; give parameters as --ros-args '
                                 f'-p {name}:=3 (see --help)')
    assert module.command_line_problem([tool, '--ros-args', '-p', f'{name}:=3']) is None
    assert module.command_line_problem([tool, 'use_sim_time:=true'])[0] == 2   # (rclpy's)


def test_the_calibrator_command_line_refuses_what_ros_would_silently_ignore(capsys):
    # `calibrator --help` started the node (and moved a journal aside); `setup:=eye_to_hand`
    # outside --ros-args is a topic remap to ROS, and `--setup eye_to_hand` was dropped.
    from quatcal_ros.ros import node
    assert node.main(['calibrator', '--help']) == 0
    said = capsys.readouterr().out
    assert said.startswith('usage: ros2 run quatcal_ros calibrator [--ros-args [-p '
                           'NAME:=VALUE ...] [--params-file FILE.yaml]')
    assert all(f'\n  {setting.name} (' in said for setting in SETTINGS)
    assert not rclpy.ok()   # nothing started
    assert parameters.command_line_problem(['calibrator', '--ros-args', '--help'])[0] == 0
    assert node.main(['calibrator', 'setup:=eye_to_hand']) == 2
    assert capsys.readouterr().err == (
        'calibrator: error: setup:=eye_to_hand: outside --ros-args, ROS takes NAME:=VALUE for '
        'a topic remap, not a parameter; give parameters as --ros-args -p setup:=eye_to_hand '
        '(see --help)\n')
    assert node.main(['calibrator', '--setup', 'eye_to_hand', '--ros-args', '-p',
                      'invert_sensor:=true']) == 2
    assert capsys.readouterr().err == (
        'calibrator: error: unexpected argument(s) --setup eye_to_hand: ROS arguments '
        '(parameters, a params file, remaps) go after --ros-args (--ros-args -p '
        'setup:=VALUE); see --help\n')
    # What ROS takes stays the node's: a topic remap (even the old form), parameters, files.
    for line in (['link_pose:=/robot/tool0_pose'],
                 ['--ros-args', '-p', 'setup:=eye_to_hand', '-r', 'sensor_pose:=/aruco'],
                 ['--ros-args', '-r', '__node:=cal', '-p', 'link_frame:=tool0']):
        assert parameters.command_line_problem(['calibrator', *line]) is None, line
    # A params file that is not there ended rclpy.init with a traceback, then rcl's words
    # (with its C source lines).
    assert parameters.command_line_problem(
        ['calibrator', '--ros-args', '--params-file', 'no_such_calibrator.yaml']) == (
        2, '--params-file no_such_calibrator.yaml: no such file')
    assert parameters.command_line_problem(
        ['calibrator', '--ros-args', '--params-file', '/']) == (
        2, '--params-file /: not a file')
    # rcl's own refusals stay said; a list of whole and decimal numbers in plain words.
    status, said = parameters.command_line_problem(['calibrator', '--ros-args', '-p', ':=1'])
    assert status == 2 and said.startswith('the ROS arguments cannot be read: ')
    from quatcal_ros.ros import sim_cell
    assert sim_cell.command_line_problem(
        ['sim_cell', '--ros-args', '-p', 'mounting_xyz:=[0, 0, 0.1]']) == (
        2, 'a list of numbers mixes whole and decimal numbers, which ROS refuses: write each '
           'with a decimal point (e.g. [0.0, 0.0, 0.1])')


def test_a_params_file_without_the_nodes_section_is_refused(tmp_path):
    # A misspelled node key: the whole file was ignored and the defaults used.
    misspelled = tmp_path / 'misspelled.yaml'
    misspelled.write_text('calibrater:\n  ros__parameters:\n    setup: eye_to_hand\n')
    status, said = parameters.command_line_problem(
        ['calibrator', '--ros-args', '--params-file', str(misspelled)])
    assert status == 2 and said == (
        f"{misspelled}: no section for the node 'calibrator' (its top-level keys: calibrater): "
        'every parameter in it would be ignored; the section is calibrator: ros__parameters: '
        '...')
    for key in ('calibrator', '/calibrator', '/robot1/calibrator', '/**', '/**/calibrator'):
        right = tmp_path / 'right.yaml'
        right.write_text(f'{key}:\n  ros__parameters:\n    setup: eye_to_hand\n')
        assert parameters.command_line_problem(
            ['calibrator', '--ros-args', '--params-file', str(right)]) is None, key
    # A node renamed at start has its own section.
    for rule in ('__node:=cal', 'calibrator:__node:=cal', '__name:=cal'):
        renamed = ['calibrator', '--ros-args', '-r', rule, '--params-file']
        right.write_text('cal:\n  ros__parameters:\n    setup: eye_to_hand\n')
        assert parameters.command_line_problem(renamed + [str(right)]) is None, rule
        right.write_text('calibrator:\n  ros__parameters:\n    setup: eye_to_hand\n')
        assert parameters.command_line_problem(renamed + [str(right)])[0] == 2, rule
