"""
`python -m quatcal_ros demo`: the calibrator against the simulated cell, until it converges.

Runs the sim_cell node and the calibrator node in one process (a private rclpy Context, one
executor), prints a line per new estimate, and at the end the estimated rotation with its
uncertainty, the simulator's ground truth (from /sim_cell/ground_truth) and the true error,
the translation's too.
The robot stops and moves faster than sim_cell's defaults so the demo takes under a minute.

Exit status: 0 when the estimate converged (uncertainty below --uncertainty-deg, or
--max-samples samples) and the true error is within 3x the reported uncertainty; 1 otherwise
(the message says why); 2 for bad arguments; 130 on Ctrl-C.
"""

import argparse
import math
import os
import sys
import tempfile
import time

from geometry_msgs.msg import TransformStamped
import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.ros import conversions
from quatcal_ros.ros.diagnostics import status_message
from quatcal_ros.ros.node import CalibratorNode
from quatcal_ros.ros.qos import LATCHED_QOS
from quatcal_ros.ros.sim_cell import PARAMETERS as SIM_PARAMETERS, SimCell
from quatcal_ros.stream.settings import ConfigError, SETTING_BY_NAME
from quatcal_ros.tools.options import HelpFormatter
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor
from rclpy.logging import LoggingSeverity
from rclpy.parameter import Parameter

ERROR_FACTOR = 3.0   # the true error must be within this many reported uncertainties


def parse_args(argv):
    """Command-line options (argv without the program name)."""
    parser = argparse.ArgumentParser(
        prog='demo', formatter_class=HelpFormatter,
        description='Calibrate a simulated cell with the live calibrator node and compare the '
                    'estimate with the ground truth.')
    parser.add_argument('--seed', type=int, default=7, help='seed of the simulated cell')
    parser.add_argument('--setup', choices=('eye_in_hand', 'eye_to_hand'),
                        default='eye_in_hand',
                        help='eye_in_hand: the camera rides on the robot link; eye_to_hand: '
                             'it stands in the cell and the marker rides on the link '
                             '(default eye_in_hand)')
    parser.add_argument('--uncertainty-deg', type=float, default=0.1,
                        help='stop when the reported uncertainty is below this (deg)')
    parser.add_argument('--max-samples', type=int, default=60,
                        help='or stop after this many samples')
    parser.add_argument('--time-limit-s', type=float, default=120.0,
                        help='give up after this much wall time (s)')
    parser.add_argument('--still-s', type=float, default=0.5,
                        help='time the robot stands still at each stop (s)')
    parser.add_argument('--move-s', type=float, default=0.5,
                        help='time of each move between stops (s)')
    parser.add_argument('--noise-deg', type=float, default=0.2,
                        help='sensor rotation noise, std per axis and frame (deg)')
    parser.add_argument('--outlier-fraction', type=float, default=0.0,
                        help='probability that a sensor frame is a marker flip')
    parser.add_argument('--verbose', action='store_true', help="show the nodes' own logs")
    args = parser.parse_args(argv)
    if not (args.uncertainty_deg > 0 and args.max_samples >= 3 and args.time_limit_s > 0):
        parser.error('need --uncertainty-deg > 0, --max-samples >= 3 and --time-limit-s > 0')
    for option, parameter in SIM_OPTIONS.items():
        low, high = SIM_PARAMETERS[parameter][2]
        value = getattr(args, option)
        if not low <= value <= high:   # (NaN fails too)
            low, high, value = (f'{v:g}' if isinstance(v, float) else v
                                for v in (low, high, value))   # (an int seed in full)
            parser.error(f'--{option.replace("_", "-")} must be within {low} to {high} '
                         f"(the simulated cell's {parameter}), not {value}")
    if args.still_s < 0.3:
        parser.error('need --still-s >= 0.3 (the still window is 0.25 s)')
    return args


# The demo's options that set the simulated cell, by its parameter (their limits are its).
SIM_OPTIONS = {'seed': 'seed', 'still_s': 'still_s', 'move_s': 'move_s',
               'noise_deg': 'rotation_noise_deg', 'outlier_fraction': 'outlier_fraction'}


def _sim_parameters(args):
    return [Parameter('seed', value=args.seed), Parameter('setup', value=args.setup),
            Parameter('still_s', value=float(args.still_s)),
            Parameter('move_s', value=float(args.move_s)),
            Parameter('rotation_noise_deg', value=float(args.noise_deg)),
            Parameter('outlier_fraction', value=float(args.outlier_fraction)),
            Parameter('rotation_spread_deg', value=45.0),
            Parameter('link_rate_hz', value=100.0)]


def _calibrator_parameters(args):
    link_frame = 'tool0' if args.setup == 'eye_in_hand' else 'base_link'
    return [Parameter('setup', value=args.setup), Parameter('link_frame', value=link_frame),
            Parameter('still_window_s', value=0.25),
            Parameter('sensor_still_rotation_deg', value=sensor_band_deg(args.noise_deg))]


def sensor_band_deg(noise_deg):
    """
    Return the sensor's still band for the simulated noise: the default, or wider.

    Two frames' rotations (noise_deg per axis each) differ by sqrt(6) noise_deg RMS; at twice
    that most frames of a stop lie within the band (at most a quarter may pass it). With the
    default noise, the default band (1 deg), as a user's calibrator has; at most the
    setting's largest (30 deg, from 6.1 deg of noise on).
    """
    band = SETTING_BY_NAME['sensor_still_rotation_deg']
    return min(max(band.default, 2.0 * math.sqrt(6.0) * noise_deg), band.high)


def format_xyzw(q_wxyz):
    """'(x, y, z, w)' text of a quaternion given as (w, x, y, z)."""
    return '(' + ', '.join(f'{v:+.6f}' for v in quat.xyzw_from_wxyz(q_wxyz)) + ')'


def format_xyz(position):
    """Return a position as (+x, +y, +z), metres to 4 decimals."""
    return '(' + ', '.join(f'{float(v):+.4f}' for v in position) + ')'


class Demo:
    """The two nodes, a ground-truth listener, and the loop that watches the estimate."""

    def __init__(self, args, context):
        self.args = args
        # Quieter nodes for the demo; close() puts the levels back (they are process-wide).
        self.log_levels = {} if args.verbose else {
            name: rclpy.logging.get_logger_effective_level(name)
            for name in ('sim_cell', 'calibrator', 'demo_listener')}
        for name in self.log_levels:
            rclpy.logging.set_logger_level(name, LoggingSeverity.WARN)
        self.sim = SimCell(context=context, parameter_overrides=_sim_parameters(args))
        # The demo's samples journal goes to a temporary directory, not ~/.ros/quatcal, so it
        # never moves a real session's journal aside.
        self.journal_dir = tempfile.TemporaryDirectory(prefix='quatcal_demo_')
        self.calibrator = CalibratorNode(
            context=context, parameter_overrides=_calibrator_parameters(args) + [Parameter(
                'samples_file', value=os.path.join(self.journal_dir.name, 'samples.csv'))])
        self.listener = rclpy.create_node('demo_listener', context=context)
        self.truth = None
        self.listener.create_subscription(TransformStamped, '/sim_cell/ground_truth',
                                          self._on_truth, LATCHED_QOS)
        self.executor = SingleThreadedExecutor(context=context)
        for node in (self.sim, self.calibrator, self.listener):
            self.executor.add_node(node)

    def _on_truth(self, msg):
        self.truth = conversions.pose_from_msg(msg)

    def converged(self, result):
        return result is not None and (result.uncertainty_deg < self.args.uncertainty_deg
                                       or result.samples >= self.args.max_samples)

    def run(self):
        """Spin until convergence or the time limit; return the last result (or None)."""
        deadline = time.monotonic() + self.args.time_limit_s
        shown_samples = 0
        while time.monotonic() < deadline:
            self.executor.spin_once(timeout_sec=0.05)
            session = self.calibrator.session
            if len(session.samples) > shown_samples:
                shown_samples = len(session.samples)
                print(progress_line(shown_samples, session), flush=True)
            if self.converged(session.result) and self.truth is not None:
                break
        return self.calibrator.session.result

    def status(self):
        """Return the calibrator's state in the words of its /diagnostics."""
        node = self.calibrator
        return status_message(node.session, node.stats, node.inputs.topics)

    def close(self):
        self.executor.shutdown()
        for node in (self.listener, self.calibrator, self.sim):
            node.destroy_node()
        self.journal_dir.cleanup()
        for name, level in self.log_levels.items():
            rclpy.logging.set_logger_level(name, level)


def progress_line(samples, session):
    """One line per new sample: the estimate and its uncertainty, or why there is none."""
    result = session.result
    count = f'{samples} sample{"s" if samples != 1 else ""}'   # (the node numbers from 0)
    if result is None:
        return f'{count}: no estimate yet (needs motions about two different axes)'
    return (f'{count}: estimate x, y, z, w = {format_xyzw(result.quaternion)}, '
            f'uncertainty {result.uncertainty_deg:.3f} deg, residual '
            f'{result.residual_rms_deg:.3f} deg')


def report(args, result, truth, status=''):
    """Print the final lines; return the exit status (status: the calibrator's state)."""
    if result is None:
        print(f'FAILED: no estimate within {args.time_limit_s:g} s (the calibrator: '
              f'{status})', file=sys.stderr)
        return 1
    print(f'estimated rotation (x, y, z, w): {format_xyzw(result.quaternion)}')
    print(f'estimated translation (m):       {format_xyz(result.translation)}')
    print(f'reported uncertainty:            {result.uncertainty_deg:.4f} deg, '
          f'{result.translation_uncertainty_mm:.2f} mm ({result.samples} samples, residual '
          f'{result.residual_rms_deg:.4f} deg RMS)')
    if truth is None:
        print('FAILED: no ground truth received from /sim_cell/ground_truth', file=sys.stderr)
        return 1
    error = float(np.degrees(quat.angle_between(result.quaternion, truth.quaternion)))
    error_mm = 1e3 * float(np.linalg.norm(np.asarray(result.translation) - truth.position))
    print(f'ground truth (x, y, z, w):       {format_xyzw(truth.quaternion)}')
    print(f'ground truth translation (m):    {format_xyz(truth.position)}')
    print(f'true error:                      {error:.4f} deg, {error_mm:.2f} mm')
    if result.uncertainty_deg >= args.uncertainty_deg and result.samples < args.max_samples:
        print(f'FAILED: not converged within {args.time_limit_s:g} s (uncertainty '
              f'{result.uncertainty_deg:.3f} deg, target {args.uncertainty_deg:g} deg)',
              file=sys.stderr)
        return 1
    for what, off, reported, unit in (('rotation', error, result.uncertainty_deg, 'deg'),
                                      ('translation', error_mm,
                                       result.translation_uncertainty_mm, 'mm')):
        if not off <= ERROR_FACTOR * reported:
            print(f'FAILED: the true {what} error {off:.4f} {unit} exceeds {ERROR_FACTOR:g}x '
                  f'the reported uncertainty ({ERROR_FACTOR * reported:.4f} {unit})',
                  file=sys.stderr)
            return 1
    print(f'OK: the true errors are within {ERROR_FACTOR:g}x the reported uncertainties')
    return 0


def main(argv=None):
    """Run the demo; see the module docstring for the exit status."""
    args = parse_args(sys.argv[1:] if argv is None else argv)
    context = Context()
    rclpy.init(context=context)
    demo = None
    try:
        demo = Demo(args, context)
        print(f'demo: {args.setup} cell, seed {args.seed}; target uncertainty '
              f'{args.uncertainty_deg:g} deg', flush=True)
        result = demo.run()
        return report(args, result, demo.truth, demo.status())
    except ConfigError as error:   # (a parameter the demo derives, out of its range)
        print(f'demo: error: {error}', file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print('demo: interrupted', file=sys.stderr)
        return 130
    finally:
        if demo is not None:
            demo.close()
        rclpy.try_shutdown(context=context)


if __name__ == '__main__':
    sys.exit(main())
