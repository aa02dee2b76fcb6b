#!/usr/bin/env python3
"""
Check that the uncertainty is honest on real recordings and the outlier decisions stable.

For each recording in data/ (the ETH arm recording, captured still-by-still from its continuous
motion as the replay does; the MoveIt samples):
- half-sample yardstick: the RMS deviation of `--halves` random half-sample estimates from the
  full estimate, divided by the halves' own reported uncertainty times sqrt(1/2) (1 = honest:
  a half's error against the full answer has the variance of the half minus that of the full,
  half of the half's variance for independent samples);
- leave-one-out stability: removing any one sample changes the rejected set by at most that
  sample (counted: how many removals changed it otherwise);
- the validation verdict and the leave-one-out prediction errors;
- the scale of the sensor's positions (core/sensor_scale.py): as recorded (1 expected), and
  whether it is named with the positions scaled by 1.02 (a board 2 % too large) and with the
  camera's depth alone scaled by 1.03 (a focal length 3 % off), beside the validation verdict
  of those, which does not see them.
Run: python bench/bench_honesty.py [--halves 40]
"""

import argparse
from pathlib import Path

import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.core.pose import Pose
from quatcal_ros.files.importers import read_moveit_json_samples
from quatcal_ros.files.pose_streams import read_pose_stream
from quatcal_ros.sim import simulation
from quatcal_ros.stream.capture import CaptureConfig
from quatcal_ros.stream.session import Session, SessionConfig

DATA = Path(__file__).resolve().parent.parent / 'data'


def eth_samples():
    """Return the ETH recording's still samples, captured as `replay --capture continuous` does."""
    folder = DATA / 'ethz_robot_arm_real'

    def load(name):
        stamps, positions, quaternions = read_pose_stream(folder / name)
        return [(s, Pose(p, q)) for s, p, q in zip(stamps, positions, quaternions)]
    link, camera = load('link_hinge_in_base.csv'), load('ir_camera_in_target.csv')
    session = Session(SessionConfig(capture=CaptureConfig(mode='continuous'),
                                    calibration=CalibrationOptions(invert_sensor=True)))
    messages = sorted([(s, 0, p) for s, p in link] + [(s, 1, p) for s, p in camera],
                      key=lambda m: m[:2])
    for stamp, stream, pose in messages:
        (session.add_link_pose if stream == 0 else session.add_sensor_pose)(stamp, pose)
    return list(session.samples)


RECORDINGS = {
    'ETH arm (eye-in-hand)': (eth_samples, {'invert_sensor': True}),
    'MoveIt (eye-to-hand)': (lambda: read_moveit_json_samples(
        DATA / 'moveit_pose_samples' / 'pose_samples.json'), {'setup': 'eye_to_hand'}),
}


def angle_deg(a, b):
    return float(np.degrees(quat.angle_between(a, b)))


def yardstick(samples, options, halves, rng):
    """Return the half-sample ratios (rotation, translation) of the published estimate."""
    full = calibrate(samples, options)
    rotation, translation, u_rotation, u_translation = [], [], [], []
    n = len(samples)
    for _ in range(halves):
        pick = np.sort(rng.choice(n, n // 2, replace=False))
        half = calibrate([samples[k] for k in pick], options)
        rotation.append(angle_deg(half.quaternion, full.quaternion))
        translation.append(1e3 * np.linalg.norm(half.translation - full.translation))
        u_rotation.append(half.uncertainty_deg)
        u_translation.append(half.translation_uncertainty_mm)

    def ratio(errors, reported):
        return float(np.sqrt(np.mean(np.square(errors)))
                     / (np.sqrt(np.mean(np.square(reported))) * np.sqrt(0.5)))
    return ratio(rotation, u_rotation), ratio(translation, u_translation), full


def stability(samples, options, full):
    """Return how many single-sample removals changed the rejected set by more than it."""
    def bad(result):
        return {r['sample'] for r in result.rejected if 'sample' in r}
    base = bad(full)
    changed = 0
    for k in range(len(samples)):
        rest = calibrate(samples[:k] + samples[k + 1:], options)
        renumbered = {s + (s >= k) for s in bad(rest)}
        if renumbered ^ (base - {k}):
            changed += 1
    return changed, len(base)


def scale_row(name, samples, options):
    """Print the sensor-scale row of one recording."""
    def judged(scale):
        wrong = simulation.scaled_sensor_positions(samples, scale, options.invert_sensor)
        result = calibrate(wrong, options)
        named = any("the sensor's positions fit the mounting best scaled" in w
                    for w in result.warnings)
        return f"{'named' if named else 'not named'}, validation {result.validation['verdict']}"
    found = calibrate(samples, options).sensor_scale
    axes = ', '.join(f'{d:.4f} +- {sd:.4f}' for d, sd in zip(found.scale, found.uncertainty))
    print(f'| {name} | {axes} | {judged(1.02)} | {judged((1.0, 1.0, 1.03))} |')


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--halves', type=int, default=40)
    args = parser.parse_args()
    print('| recording | method | samples | rejected | LOO changes | half-sample ratio rot | '
          'half-sample ratio trans | validation |')
    print('|---|---|---|---|---|---|---|---|')
    for name, (load, extra) in RECORDINGS.items():
        samples = load()
        for method in ('refined', 'closed-form'):
            options = CalibrationOptions(method=method, **extra)
            rot, trans, full = yardstick(samples, options, args.halves,
                                         np.random.default_rng(0))
            changed, rejected = stability(samples, options, full)
            v = full.validation
            verdict = (f"{v['verdict']} ({v['rms_rotation_deg']:.2f} deg, "
                       f"{v['rms_translation_mm']:.1f} mm)" if v['rms_rotation_deg'] is not None
                       else v['verdict'])
            print(f'| {name} | {method} | {len(samples)} | {rejected} | {changed} | {rot:.2f} | '
                  f'{trans:.2f} | {verdict} |')
    print('\n| recording | sensor scale x, y, z (+- 1 sd) | positions x 1.02 | depth x 1.03 |')
    print('|---|---|---|---|')
    for name, (load, extra) in RECORDINGS.items():
        scale_row(name, load(), CalibrationOptions(**extra))


if __name__ == '__main__':
    main()
