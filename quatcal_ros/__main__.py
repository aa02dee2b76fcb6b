"""
`python -m quatcal_ros TOOL [ARGS...]`: the package's tools (DESIGN.md contract 3).

The same tools are ROS executables: `ros2 run quatcal_ros TOOL`.
"""

import _signal   # the C module: `signal` builds its enums first, which takes milliseconds
import sys

NODE_TOOLS = ('calibrator', 'sim_cell', 'target_detector')
# A stop signal to a node from this line on is noted, not fatal (ros/stop_signals.py takes the
# list over). Before it, while the interpreter starts, no Python program can catch one.
EARLY_SIGNALS = []
if __name__ == '__main__' and sys.argv[1:2] and sys.argv[1] in NODE_TOOLS:
    for _signum in (_signal.SIGINT, _signal.SIGTERM):
        _signal.signal(_signum, lambda signum, frame: EARLY_SIGNALS.append(signum))

import importlib  # noqa: E402,I100 - after the signal guard
import os  # noqa: E402

from quatcal_ros.core.threads import single_threaded_blas  # noqa: E402

TOOLS = {
    'solve': ('quatcal_ros.tools.cli', 'solve_main',
              'the mounting from a samples file or an image folder (prints JSON)'),
    'replay': ('quatcal_ros.tools.cli', 'replay_main',
               'the mounting from a rosbag2 recording (prints JSON)'),
    'calibrator': ('quatcal_ros.ros.node', 'main', 'the live calibration node'),
    'sim_cell': ('quatcal_ros.ros.sim_cell', 'main', 'a simulated robot cell (ROS node)'),
    'target_detector': ('quatcal_ros.ros.target_detector', 'main',
                        'the calibration board in camera images (ROS node)'),
    'plan': ('quatcal_ros.tools.plan', 'main',
             'link poses for a fresh calibration (prints YAML)'),
    'demo': ('quatcal_ros.tools.demo', 'main',
             'calibrator against the simulated cell, until it converges'),
    'poses_to_bag': ('quatcal_ros.tools.poses_to_bag', 'main',
                     'two pose-stream files (t x y z qx qy qz qw) as a bag for replay'),
}


def usage():
    """Return the list of tools."""
    lines = ['usage: python -m quatcal_ros TOOL [ARGS...]', '', 'tools:']
    width = max(len(name) for name in TOOLS)
    lines += [f'  {name:<{width}}  {text}' for name, (_, _, text) in TOOLS.items()]
    return '\n'.join(lines)


def main(argv=None):
    """Run the tool named by the first argument with the remaining arguments."""
    argv = sys.argv[1:] if argv is None else argv
    if not argv or argv[0] in ('-h', '--help'):
        print(usage())
        return 0 if argv else 2
    if argv[0] not in TOOLS:
        from quatcal_ros.files.text_input import typo_of
        close = typo_of(argv[0], TOOLS)
        meant = f' (did you mean {close}?)' if close else ''
        print(f'quatcal_ros: unknown tool {argv[0]!r}{meant}\n{usage()}', file=sys.stderr)
        return 2
    module, function, _ = TOOLS[argv[0]]
    single_threaded_blas()
    if argv[0] in NODE_TOOLS:
        # ROS nodes take rclpy's argument list (with --ros-args) including a program name;
        # a stop signal while they import ends them cleanly too.
        from quatcal_ros.ros import stop_signals
        stop_signals.guard()   # first: a signal from now on goes to its list...
        stop_signals.received[:0] = EARLY_SIGNALS   # ... after those noted before
        return stop_signals.run(module, [argv[0]] + argv[1:]) or 0
    tool_main = getattr(importlib.import_module(module), function)
    try:
        return tool_main(argv[1:]) or 0
    except BrokenPipeError:   # the reader of the output left (`... | head`): no traceback
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1


def solve():
    """Entry point of `ros2 run quatcal_ros solve`."""
    sys.exit(main(['solve', *sys.argv[1:]]))


def replay():
    """Entry point of `ros2 run quatcal_ros replay`."""
    sys.exit(main(['replay', *sys.argv[1:]]))


def plan():
    """Entry point of `ros2 run quatcal_ros plan`."""
    sys.exit(main(['plan', *sys.argv[1:]]))


def demo():
    """Entry point of `ros2 run quatcal_ros demo`."""
    sys.exit(main(['demo', *sys.argv[1:]]))


def poses_to_bag():
    """Entry point of `ros2 run quatcal_ros poses_to_bag`."""
    sys.exit(main(['poses_to_bag', *sys.argv[1:]]))


if __name__ == '__main__':
    sys.exit(main())
