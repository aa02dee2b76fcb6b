"""
`plan`: the link poses of a fresh calibration, as YAML a motion script or MoveIt can replay.

From a start pose of the link (T_base_link), a guess of the mounting and of the object's pose,
and the limits (largest turn between poses, view cone, workspace box), core.planner's
plan_session chooses each next pose as the one that most shrinks the expected uncertainty
(D-optimal on the mounting). The guesses shape only the geometry (where the target stays in
view); the calibration itself needs no guess. Prints or writes:

    frame: base_link            # the frame of the link poses (robot base)
    setup: eye_in_hand
    poses:
    - position: {x: .., y: .., z: ..}
      orientation: {x: .., y: .., z: .., w: ..}
      expected_uncertainty_deg: ..          # after this pose (null for the start)
      expected_translation_uncertainty_mm: ..
"""

import argparse
import sys

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.numerics import finite_or_none
from quatcal_ros.core.planner import plan_session, PlanLimits
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.units import FILE_NORM_TOLERANCE, MAX_POSITION_M, \
    quaternion_norm_problem
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.persistence import atomic_write_text
from quatcal_ros.tools.options import add_setting_options, HelpFormatter

EXIT_BAD_INPUT = 2
# The workspace box around the start position when none is given, half-width in metres.
DEFAULT_BOX_HALF_M = 0.25


def parser():
    """Return the argument parser of `plan`."""
    parse = argparse.ArgumentParser(
        prog='plan', formatter_class=HelpFormatter,
        description='Link poses for a fresh hand-eye calibration, each chosen to shrink the '
                    'expected uncertainty most (D-optimal); prints YAML.')
    parse.add_argument('--start', nargs=7, type=float, required=True,
                       metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                       help='the start pose of the link, T_base_link (m; quaternion x y z w)')
    parse.add_argument('--count', type=int, default=15,
                       help='number of poses, the start included (default 15)')
    add_setting_options(parse, 'plan', ('setup',))
    parse.add_argument('--mounting', nargs=7, type=float,
                       metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                       help='guess of the mounting: T_link_sensor (eye_in_hand; default: the '
                            'link frame) or T_base_sensor (eye_to_hand; required)')
    target = parse.add_mutually_exclusive_group()
    target.add_argument('--target-distance', type=float, default=0.5, metavar='M',
                        help='eye_in_hand: the target lies this far along the sensor z axis '
                             'at the start pose (default 0.5 m)')
    target.add_argument('--object', nargs=7, type=float,
                        metavar=('X', 'Y', 'Z', 'QX', 'QY', 'QZ', 'QW'),
                        help='the observed object instead: T_base_object (eye_in_hand) or '
                             'T_link_object (eye_to_hand; default: the link frame)')
    parse.add_argument('--box-min', nargs=3, type=float, metavar=('X', 'Y', 'Z'),
                       help='workspace box of the link position, base frame (default: the '
                            f'start position -{DEFAULT_BOX_HALF_M:g} m)')
    parse.add_argument('--box-max', nargs=3, type=float, metavar=('X', 'Y', 'Z'),
                       help=f'(default: the start position +{DEFAULT_BOX_HALF_M:g} m)')
    parse.add_argument('--noise-deg', type=float, default=0.1,
                       help='expected sensor rotation noise per axis (default 0.1 deg)')
    parse.add_argument('--noise-mm', type=float, default=1.0,
                       help='expected sensor translation noise per axis (default 1 mm)')
    parse.add_argument('--frame', default='base_link',
                       help='the robot base frame named in the output (default base_link)')
    parse.add_argument('--seed', type=int, default=0, help='seed of the random candidates')
    parse.add_argument('--out', metavar='FILE.yaml', help='write the YAML there (atomically)')
    add_setting_options(parse, 'plan', ('plan_max_rotation_deg', 'plan_view_cone_deg'))
    return parse


def _pose(values, name):
    """Return the Pose of 7 numbers x y z qx qy qz qw; ValueError naming `name`."""
    values = np.asarray(values, float)
    if not np.all(np.isfinite(values)):
        raise ValueError(f'{name}: 3 finite coordinates and a quaternion x y z w')
    _check_position(values[:3], name)
    problem = quaternion_norm_problem(values[3:], FILE_NORM_TOLERANCE)
    if problem is not None:
        raise ValueError(f'{name}: {problem}')
    return Pose.create(values[:3], quat.normalize(quat.wxyz_from_xyzw(values[3:])))


def _check_position(values, name):
    """Raise ValueError naming `name` for a position no robot cell has."""
    if not np.all(np.isfinite(values)) or np.max(np.abs(values)) > MAX_POSITION_M:
        raise ValueError(f'{name}: {np.asarray(values).tolist()} m is not a position in a '
                         f'robot cell (finite, within {MAX_POSITION_M:g} m)')


def _check_options(args):
    """Raise ValueError naming the first option whose number no plan can use."""
    if args.count < 2:
        raise ValueError(f'--count must be at least 2, not {args.count}')
    # Noise below 1e-4 deg or 1 um (no sensor's) made the planner's information singular.
    for name, value, low, top in (('--noise-deg', args.noise_deg, 1e-4, 90.0),
                                  ('--noise-mm', args.noise_mm, 1e-3, 1e3 * MAX_POSITION_M)):
        if not low <= value <= top:   # (NaN fails too)
            raise ValueError(f'{name} must be a number from {low:g} to {top:g}, not {value:g}')
    if not 0.0 < args.target_distance <= MAX_POSITION_M:
        raise ValueError(f'--target-distance must be a positive number up to '
                         f'{MAX_POSITION_M:g}, not {args.target_distance:g}')
    for name, values in (('--box-min', args.box_min), ('--box-max', args.box_max)):
        if values is not None:
            _check_position(values, name)


def _guesses(args, start):
    """Return (mounting, object pose) of the options (module docstring)."""
    identity = Pose.create([0.0, 0.0, 0.0], np.array([1.0, 0.0, 0.0, 0.0]))
    if args.setup == 'eye_to_hand':
        if args.mounting is None:
            raise ValueError('--mounting is required for eye_to_hand: a guess of T_base_sensor '
                             '(where the camera stands, looking at the link)')
        mounting = _pose(args.mounting, '--mounting')
        return mounting, (_pose(args.object, '--object') if args.object else identity)
    mounting = _pose(args.mounting, '--mounting') if args.mounting else identity
    if args.object:
        return mounting, _pose(args.object, '--object')
    ahead = Pose.create([0.0, 0.0, args.target_distance], np.array([1.0, 0.0, 0.0, 0.0]))
    return mounting, start @ mounting @ ahead


def plan_document(args):
    """Return the YAML document of the options' plan; ValueError for unusable options."""
    _check_options(args)
    start = _pose(args.start, '--start')
    mounting, target = _guesses(args, start)
    low = np.asarray(args.box_min if args.box_min else start.position - DEFAULT_BOX_HALF_M)
    high = np.asarray(args.box_max if args.box_max else start.position + DEFAULT_BOX_HALF_M)
    if not np.all(low <= high):   # (equal: a flat box, one height)
        axes = ', '.join(axis for axis, a, b in zip('xyz', low, high) if not a <= b)
        raise ValueError(f'--box-min {low.tolist()} is not below --box-max {high.tolist()} '
                         f'along {axes}: the first corner is the smallest x, y and z')
    if not np.all(low <= start.position) or not np.all(start.position <= high):
        raise ValueError(f'the start position {start.position.tolist()} lies outside the box '
                         f'{low.tolist()} .. {high.tolist()}')
    seen = mounting.inverse() @ (start.inverse() @ target if args.setup == 'eye_in_hand'
                                 else start @ target)
    off_axis = np.degrees(np.arctan2(np.linalg.norm(seen.position[:2]), seen.position[2]))
    if off_axis > args.plan_view_cone_deg:
        raise ValueError(f"the object is {off_axis:.0f} deg off the sensor's optical axis at "
                         f'the start pose (view cone {args.plan_view_cone_deg:g} deg): check '
                         '--mounting and --object, or start where the sensor sees the object')
    limits = PlanLimits(max_rotation_deg=args.plan_max_rotation_deg,
                        cone_deg=args.plan_view_cone_deg, box_min=tuple(low),
                        box_max=tuple(high), seed=args.seed)
    planned = plan_session(start, args.count, mounting, target, args.setup,
                           (args.noise_deg, args.noise_mm), limits)
    poses = []
    for step in planned:
        poses.append({
            'position': quat.xyz_json(step.link.position),
            'orientation': quat.xyzw_json(step.link.quaternion),
            'expected_uncertainty_deg': finite_or_none(step.uncertainty_deg),
            'expected_translation_uncertainty_mm': finite_or_none(
                step.translation_uncertainty_mm)})
    return {'frame': args.frame, 'setup': args.setup, 'poses': poses,
            'limits': {'max_rotation_deg': limits.max_rotation_deg,
                       'view_cone_deg': limits.cone_deg,
                       'box_min': low.tolist(), 'box_max': high.tolist()}}


def main(argv=None):
    """`plan --start ... [--count K]`: print (or --out) the poses as YAML; exit 2 if unusable."""
    args = parser().parse_args(argv)
    try:
        document = plan_document(args)
    except ValueError as error:
        print(f'plan: error: {error}', file=sys.stderr)
        return EXIT_BAD_INPUT
    if len(document['poses']) < args.count:
        print(f'plan: warning: only {len(document["poses"])} of {args.count} poses fit the '
              'limits (widen --box-min/--box-max or --plan-max-rotation-deg)', file=sys.stderr)
    text = plain_yaml.dump(document, sort_keys=False)
    if args.out:
        try:
            atomic_write_text(args.out, text)
        except OSError as error:
            print(f'plan: error: {args.out}: cannot write: {error}', file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f'plan: info: {len(document["poses"])} poses written to {args.out}',
              file=sys.stderr)
    else:
        write_stdout(text)
    return 0


def write_stdout(text):
    """Print `text`; as UTF-8 bytes when the terminal's encoding cannot hold it (YAML's)."""
    try:
        sys.stdout.write(text)   # encoded whole before any byte is written
    except UnicodeEncodeError:
        sys.stdout.flush()
        sys.stdout.buffer.write(text.encode('utf-8'))
        sys.stdout.buffer.flush()
