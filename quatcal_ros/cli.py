"""
Command-line tools of DESIGN.md contract 3 that run without ROS: `solve`.

Exit status: 0 success; 2 bad input or arguments (stderr names file, row and field); 3 the
data cannot determine the rotation (stderr says why and what motion would help).
"""

import argparse
import json
import sys

from quatcal_ros.calibration import CalibrationOptions
from quatcal_ros.samples_csv import BadInputError, read_samples
from quatcal_ros.session import Session, SessionConfig

EXIT_BAD_INPUT = 2
EXIT_UNDETERMINED = 3


def add_estimator_arguments(parser):
    """Options shared by `solve` and `replay`: how samples become an estimate."""
    parser.add_argument('--setup', choices=('eye_in_hand', 'eye_to_hand'),
                        default='eye_in_hand',
                        help='eye_in_hand: sensor on the link, answer link -> sensor; '
                             'eye_to_hand: sensor fixed, answer base -> sensor')
    parser.add_argument('--pairs', choices=('all', 'consecutive'), default='all',
                        help='which sample pairs form motions (default: all pairs)')
    parser.add_argument('--no-robust', action='store_true',
                        help='plain least squares: no outlier screening or rejection')
    parser.add_argument('--invert-sensor', action='store_true',
                        help='the sensor poses are the sensor in the object frame '
                             '(inverse of the usual detector output)')
    parser.add_argument('--min-motion-deg', type=float, default=5.0,
                        help='motions rotating less are not used (default 5)')


def estimator_options(args):
    """Build the CalibrationOptions of parsed arguments."""
    return CalibrationOptions(setup=args.setup, pairs=args.pairs, robust=not args.no_robust,
                              invert_sensor=args.invert_sensor,
                              min_motion_deg=args.min_motion_deg)


def solve_main(argv=None):
    """`solve SAMPLES.csv`: estimate the rotation from a samples CSV, print JSON."""
    parser = argparse.ArgumentParser(
        prog='solve', description='Hand-eye rotation (Chou-Kamel) from a samples CSV; '
                                  'prints one JSON object.')
    parser.add_argument('samples', help='samples CSV (DESIGN.md contract 2)')
    add_estimator_arguments(parser)
    args = parser.parse_args(argv)
    try:
        samples = read_samples(args.samples)
    except BadInputError as error:
        return fail(parser.prog, error, EXIT_BAD_INPUT)
    session = Session(SessionConfig(calibration=estimator_options(args)))
    session.add_samples(samples)
    return print_result(parser.prog, session, f'{args.samples}: ')


def print_result(prog, session, where=''):
    """Print the session's result as JSON (exit 0) or why there is none (exit 2 or 3)."""
    if len(session.samples) < 3:
        return fail(prog, f'{where}{len(session.samples)} sample(s); at least 3 are needed',
                    EXIT_BAD_INPUT)
    if session.result is None:
        return fail(prog, f'{where}the rotation cannot be determined: {session.last_error}',
                    EXIT_UNDETERMINED)
    print(json.dumps(session.result.to_json_dict(), indent=2))
    return 0


def fail(prog, message, status):
    """Print `prog: error: message` on stderr and return `status`."""
    print(f'{prog}: error: {message}', file=sys.stderr)
    return status


if __name__ == '__main__':
    sys.exit(solve_main())
