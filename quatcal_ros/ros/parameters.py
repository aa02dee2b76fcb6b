"""
The calibrator node's parameters: the settings table (stream/settings.py) as ROS parameters.

Every setting is declared with a ParameterDescriptor (description, range, read_only) made from
its table row.  The values are checked together into a frozen `Settings`; the same checks run
at startup (`declare_parameters`, which raises ConfigError with the reason) and at runtime
(`updated`, used by the node's set-parameters callback).  `use_sim_time` is rclpy's own and is
not declared here.  `params_file_text` renders config/calibrator.yaml from the table.
"""

import re
import textwrap

from quatcal_ros.ros import command_line
from quatcal_ros.stream.settings import CAPTURE, check_writable, ConfigError, FILES, \
    NODE_NAME, PRESENTATION, SETTING_BY_NAME
from quatcal_ros.stream.settings import SETTINGS
from quatcal_ros.stream.settings import Settings
from rcl_interfaces.msg import FloatingPointRange
from rcl_interfaces.msg import IntegerRange
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter
import yaml

__all__ = ['command_line_problem', 'ConfigError', 'declare_parameters', 'descriptor', 'help_text',
           'params_file_text', 'updated']


def descriptor(setting):
    """Return the ParameterDescriptor declared with `setting`."""
    result = ParameterDescriptor(
        name=setting.name, description=setting.description,
        additional_constraints=setting.constraints, read_only=setting.read_only)
    if isinstance(setting.default, bool) or setting.low is None:
        return result
    if isinstance(setting.default, int):
        result.integer_range = [IntegerRange(from_value=int(setting.low),
                                             to_value=int(setting.high), step=0)]
    else:
        result.floating_point_range = [FloatingPointRange(
            from_value=float(setting.low), to_value=float(setting.high), step=0.0)]
    return result


def declare_parameters(node):
    """
    Declare every setting on `node` as a parameter and return the checked Settings.

    :raises ConfigError: with the reason, for a value of the wrong type, out of range, or not
        one of the allowed choices (from parameter_overrides or --ros-args -p).
    """
    command_line.accept_integers_for_reals(node, {
        setting.name: Parameter.Type.DOUBLE for setting in SETTINGS
        if type(setting.default) is float})
    for setting in SETTINGS:
        try:
            node.declare_parameter(setting.name, setting.default, descriptor(setting))
        except ParameterException as error:
            given = getattr(node, '_parameter_overrides', {}).get(setting.name)
            # The table's own words (rclpy's repeat the name: '... out of range Min: 0.05,
            # Max: 10.0, value: 20.0: still_window_s').
            problem = setting.check(given.value) if given is not None else None
            if problem:
                raise ConfigError(f'parameter {setting.name} {problem}') from None
            raise ConfigError(f'parameter {setting.name}: {error}') from None
    command_line.refuse_unknown_parameters(node, SETTING_BY_NAME, NODE_NAME, ConfigError)
    settings = Settings.from_values(
        {setting.name: node.get_parameter(setting.name).value for setting in SETTINGS})
    check_writable(settings)
    return settings


def updated(settings, parameters):
    """
    Return the Settings after setting `parameters` (rclpy Parameter objects).

    :raises ConfigError: when a new value is not allowed; `settings` stay as they were.
    """
    new = settings.updated(**{p.name: p.value for p in parameters if p.name in SETTING_BY_NAME})
    # (the files set now: one whose folder became read-only since does not block the others)
    check_writable(new, [p.name for p in parameters if p.name in FILES])
    return new


def params_file_text():
    """Return the text of config/calibrator.yaml: every parameter, its default and comment."""
    lines = [
        '# Parameters of the quatcal_ros calibrator node, with their defaults.',
        '# Use: ros2 run quatcal_ros calibrator --ros-args --params-file calibrator.yaml',
        '# Generated from the settings table (quatcal_ros/stream/settings.py):',
        '#   python -m quatcal_ros.ros.parameters > config/calibrator.yaml',
        '# A whole number is taken for a real-valued parameter (1 for 1.0).',
        '# read-only: set at startup only; every other parameter can be changed at runtime',
        '# (ros2 param set), and the estimate is recomputed from the samples so far, except',
        '# for those marked "keeps the estimate" (they change only the outputs, the checks or',
        '# how samples are taken).',
        f'{NODE_NAME}:',
        '  ros__parameters:',
    ]
    for setting in SETTINGS:
        lines += textwrap.wrap(_described(setting), 95, initial_indent='    # ',
                               subsequent_indent='    # ')
        lines.append(f'    {setting.name}: {_yaml_value(setting.default)}')
    return '\n'.join(lines) + '\n'


def _described(setting):
    """Return the setting's description with its constraints and whether it can change."""
    notes = [setting.constraints] if setting.constraints else []
    if setting.read_only:
        notes.append('read-only')
    elif setting.name in PRESENTATION + CAPTURE:
        notes.append('keeps the estimate')
    return setting.description + (f' ({"; ".join(notes)})' if notes else '')


def help_text():
    """Return the calibrator's --help: how to give parameters, and each with its default."""
    return command_line.help_text(
        NODE_NAME, 'The live hand-eye calibration node: topics, services and a session step by '
        "step are in the package's README.",
        [(setting.name, _yaml_value(setting.default), _described(setting))
         for setting in SETTINGS])


def command_line_problem(arguments):
    """
    Return (exit status, text) for a command line the node must not start with, or None.

    arguments: the whole command line (program name first): command_line.problem's cases
    (--help, `--setup eye_to_hand`, the offline tools' form, a parameter outside --ros-args),
    then a params file without a section for this node.
    """
    return (command_line.problem(arguments, help_text, SETTING_BY_NAME)
            or _params_file_problem(arguments))


def _params_file_problem(arguments):
    """
    Return (2, text) for a params file with no section for this node (all of it ignored).

    A section is a top-level key whose last name is the node's (NODE_NAME, or the one
    `-r __node:=NAME` gives it) or that holds a wildcard (rcl's * and **).
    """
    ros = arguments[arguments.index('--ros-args') + 1:] if '--ros-args' in arguments else []
    node = NODE_NAME
    for flag, value in zip(ros, ros[1:]):   # (-r [NODE:]__node:=NAME, or __name:=)
        renamed = re.fullmatch(r'(?:[^:]+:)?__(?:node|name):=(.+)', value)
        if flag in ('-r', '--remap') and renamed:
            node = renamed.group(1)
    for flag, path in zip(ros, ros[1:]):
        if flag != '--params-file':
            continue
        try:
            with open(path, encoding='utf-8') as stream:
                document = yaml.safe_load(stream)
        except (OSError, UnicodeDecodeError, yaml.YAMLError):
            continue   # (rcl names what it cannot read)
        keys = [str(key) for key in document] if isinstance(document, dict) else []
        if keys and not any('*' in key or key.rstrip('/').split('/')[-1] == node
                            for key in keys):
            return 2, (f'{path}: no section for the node {node!r} (its top-level keys: '
                       f'{", ".join(keys)}): every parameter in it would be ignored; the '
                       f'section is {node}: ros__parameters: ...')
    return None


def _yaml_value(value):
    if isinstance(value, bool):
        return 'true' if value else 'false'
    if isinstance(value, str):
        plain = value and not value.startswith('~') and ':' not in value
        return value if plain else "'" + value.replace("'", "''") + "'"
    return repr(value)


if __name__ == '__main__':
    print(params_file_text(), end='')
