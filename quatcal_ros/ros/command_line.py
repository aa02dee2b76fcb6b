"""
A node's own command line: --help, and arguments that ROS would take silently for other things.

A node's parameters go after --ros-args (`-p NAME:=VALUE`); before it, ROS takes NAME:=VALUE
for a topic remap and ignores any other argument, so a mistyped command line starts the node
as if it were right (`sim_cell --help` started the cell). `problem` names those cases before
rclpy.init; spin.run prints its answer and exits (0 for --help, 2 otherwise).
"""

import os
import textwrap

from quatcal_ros.files.text_input import typo_of
from quatcal_ros.stream.settings import Setting
from rclpy.exceptions import ParameterException
from rclpy.parameter import Parameter
from rclpy.utilities import remove_ros_args

# A parameter of these types given as the integer type beside it is taken as its reals.
REALS_OF_INTEGERS = {Parameter.Type.DOUBLE: (Parameter.Type.INTEGER, float),
                     Parameter.Type.DOUBLE_ARRAY: (Parameter.Type.INTEGER_ARRAY,
                                                   lambda values: [float(v) for v in values])}


def problem(arguments, help_text, names):
    """
    Return (exit status, text) for a command line the node must not start with, or None.

    arguments: the whole command line (program name first); help_text(): the node's --help;
    names: its parameter names. --help or -h asks for help_text (0), after --ros-args too
    (rcl knows no such argument). A parameter written NAME:=VALUE outside --ros-args (2), any
    other argument the node does not know (2), a --params-file that is not a file (2), ROS
    arguments rcl cannot read (2, instead of rclpy.init's traceback; a list mixing whole and
    decimal numbers in plain words).
    """
    own = arguments[1:]
    if '--ros-args' in own:
        own = own[:own.index('--ros-args')]
    if any(argument in ('-h', '--help') for argument in arguments[1:]):   # (after too)
        return 0, help_text()
    names = set(names) | {'use_sim_time'}   # (rclpy's own, every node has it)
    misplaced = [a for a in own if a.split(':=', 1)[0] in names and ':=' in a]
    if misplaced:
        return 2, (f'{" ".join(misplaced)}: outside --ros-args, ROS takes NAME:=VALUE for a '
                   'topic remap, not a parameter; give parameters as --ros-args -p '
                   f'{misplaced[0]} (see --help)')
    for option, value in zip(arguments, arguments[1:]):   # (rcl says its own source lines)
        if option == '--params-file' and not os.path.isfile(value):
            return 2, (f'--params-file {value}: no such file'
                       if not os.path.exists(value) else f'--params-file {value}: not a file')
    try:
        unknown = remove_ros_args(arguments)[1:]
    except Exception as error:   # noqa: B902 - rcl's parse errors (rclpy.init's traceback)
        if 'Sequence should be of same type' in str(error):   # (rcl's words name its sources)
            return 2, ('a list of numbers mixes whole and decimal numbers, which ROS refuses: '
                       'write each with a decimal point (e.g. [0.0, 0.0, 0.1])')
        return 2, f'the ROS arguments cannot be read: {error}'
    if unknown:
        name = unknown[0].lstrip('-').replace('-', '_')
        example = f' (--ros-args -p {name}:=VALUE)' if name in names else ''
        return 2, (f'unexpected argument(s) {" ".join(unknown)}: ROS arguments (parameters, '
                   f'a params file, remaps) go after --ros-args{example}; see --help')
    return None


# What a list-valued parameter takes (Setting.check knows the single values).
LIST_OF_NUMBERS = "must be a list of numbers, such as '[0.0, 0.0, 0.1]'"


def declared(node, name, default, descriptor, limits=None):
    """
    Declare a parameter of a node without a settings table (sim_cell, target_detector).

    Return its value. What -p or a params file gave that rclpy refuses is a ValueError in
    the settings table's words (Setting.check): 'parameter NAME must be between LOW and
    HIGH, not VALUE' (rclpy's name the parameter twice, or end a node in a traceback).
    limits: (low, high), or None.
    """
    try:
        return node.declare_parameter(name, default, descriptor).value
    except ParameterException:
        given = node._parameter_overrides.get(name)   # (what was refused)
        if given is None:
            raise
        if default == Parameter.Type.DOUBLE_ARRAY:
            problem = f'{LIST_OF_NUMBERS}, not {given.value!r}'
        else:
            low, high = limits or (None, None)
            problem = Setting(name, default, '', low=low, high=high).check(given.value)
        if not problem:
            raise
        raise ValueError(f'parameter {name} {problem}') from None


def accept_integers_for_reals(node, real_types):
    """
    Let an integer stand for a real-valued parameter of `node`, at start and when set.

    real_types: {name: Parameter.Type.DOUBLE or DOUBLE_ARRAY}. ROS reads `-p
    still_window_s:=1` and `ros2 param set ... still_window_s 1` as an integer, which a
    parameter declared as a real refuses ('Wrong parameter type'); the meaning is plain.
    Call it before declaring: it converts the overrides rclpy keeps (-p, a params file),
    and adds a pre-set callback for every later change.
    """
    def reals(parameters):
        converted = []
        for parameter in parameters:
            integer, convert = REALS_OF_INTEGERS.get(real_types.get(parameter.name), (None, None))
            converted.append(Parameter(parameter.name, real_types[parameter.name],
                                       convert(parameter.value))
                             if integer is not None and parameter.type_ == integer
                             else parameter)
        return converted

    overrides = node._parameter_overrides   # (rclpy's: declare_parameter reads them)
    overrides.update((parameter.name, parameter) for parameter in reals(overrides.values()))
    # rclpy joins the lists its pre-set callbacks return: one per node, or each doubled.
    node.add_pre_set_parameters_callback(reals)


def refuse_unknown_parameters(node, names, node_name, error):
    """
    Raise `error` for a parameter set for `node` at start that is a typo of one of `names`.

    What -p and a params file set for this node (rclpy keeps them, declared or not): a name
    no parameter has was ignored without a word (still_windw_s, tf_mod). One close to a
    parameter's is a typo: refused. Others may be meant for other nodes (a params file's /**
    section, a launch file's global parameters): logged as ignored.
    """
    unknown = sorted(name for name in getattr(node, '_parameter_overrides', {})
                     if not node.has_parameter(name) and not name.startswith('qos_overrides.'))
    refusal = _no_such(unknown, names, node_name, typos_only=True)
    if refusal:
        raise error(refusal)
    if unknown:
        node.get_logger().warning(f'parameters set for this node that it does not have, '
                                  f'ignored: {", ".join(unknown)}')


def unknown_at_runtime(node, parameters, names, node_name):
    """
    Return the refusal of a runtime change (`ros2 param set`) to a parameter `node` lacks.

    For a node made with allow_undeclared_parameters, so that its set-parameters callback
    sees the name: rclpy's own refusal named none ('undeclared parameter(s): []').
    """
    return _no_such([p.name for p in parameters if not node.has_parameter(p.name)], names,
                    node_name)


def _no_such(unknown, names, node_name, typos_only=False):
    """Say 'no such parameter: ...' of the `unknown` names, each with the one meant; or None."""
    close = {name: typo_of(name, names) for name in unknown}
    named = [f'{name} (did you mean {close[name]}?)' if close[name] else name
             for name in unknown if close[name] or not typos_only]
    if not named:
        return None
    return f'no such parameter: {", ".join(named)}; `{node_name} --help` lists every parameter'


def help_text(node_name, about, parameters):
    """
    Return a node's --help: how to give parameters, what it is, each parameter and default.

    parameters: [(name, default, description)].
    """
    lines = [f'usage: ros2 run quatcal_ros {node_name} [--ros-args [-p NAME:=VALUE ...] '
             '[--params-file FILE.yaml] [-r TOPIC:=NEW_TOPIC ...]]', '',
             *textwrap.wrap(about, 95), '', 'parameters (default):']
    for name, default, description in parameters:
        shown = str(default).lower() if isinstance(default, bool) else default   # (as YAML)
        lines.append(f'  {name} ({shown})')
        lines += textwrap.wrap(description, 95, initial_indent='      ',
                               subsequent_indent='      ')
    return '\n'.join(lines)
