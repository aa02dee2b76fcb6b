#!/usr/bin/env python3
"""
Robots that cannot turn the link freely: ours beside OpenCV's calibrateHandEye, same samples.

Each row draws `--cells` eye-in-hand cells (quatcal_ros.sim.simulation.reduced_dof_samples):
a SCARA (the link turns about base z by up to 60 deg, moves within 15 cm) or a gantry (moves
only), 25 still samples, 0.1 deg and 1 mm sensor noise. Printed: the RMS rotation error (deg)
and the RMS error of the translation the data determine (mm: for a SCARA the part across its
axis; a gantry determines none, so the whole error is shown for OpenCV and '-' for ours, whose
undetermined part is the user's prior), and the RMS of ours' error over its reported
uncertainty (1 = honest). OpenCV has no notion of an undetermined direction: its translation
along the axis is whatever its solver returns.
Run: python bench/bench_reduced_dof.py [--cells 20]
"""

import argparse

import cv2
import numpy as np

from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate
from quatcal_ros.sim import simulation

OPENCV_METHODS = {'TSAI': cv2.CALIB_HAND_EYE_TSAI, 'PARK': cv2.CALIB_HAND_EYE_PARK,
                  'HORAUD': cv2.CALIB_HAND_EYE_HORAUD, 'ANDREFF': cv2.CALIB_HAND_EYE_ANDREFF,
                  'DANIILIDIS': cv2.CALIB_HAND_EYE_DANIILIDIS}


def opencv(samples, method):
    """OpenCV: gripper2base = T_base_link, target2cam = T_sensor_obj -> cam2gripper (X)."""
    R, t = cv2.calibrateHandEye([s.link.rotation for s in samples],
                                [s.link.position.reshape(3, 1) for s in samples],
                                [s.sensor.rotation for s in samples],
                                [s.sensor.position.reshape(3, 1) for s in samples],
                                method=method)
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        return None   # OpenCV's answer to degenerate motions: NaN
    return quat.quaternion_from_matrix(R), t.ravel()


def determined(error, axis):
    """Return the part of a translation error (m) across `axis` (all of it when None)."""
    return error if axis is None else error - np.dot(error, axis) * axis


def row(kind, cells):
    rotation = {name: [] for name in ('ours', *OPENCV_METHODS)}
    translation = {name: [] for name in rotation}
    failed = dict.fromkeys(rotation, 0)
    ratios = []
    for seed in range(cells):
        rng = np.random.default_rng(seed)
        cell = simulation.random_cell(rng)
        samples = simulation.reduced_dof_samples(rng, cell, 25, kind, 0.1, 0.001)
        result = calibrate(samples)
        axis = (np.array(result.unobservable[0]['direction']) if kind == 'scara' else None)
        ours_deg = np.degrees(quat.angle_between(result.quaternion, cell.mounting.quaternion))
        rotation['ours'].append(ours_deg)
        ratio = [ours_deg / result.uncertainty_deg]
        if kind == 'scara':
            error_mm = 1e3 * np.linalg.norm(determined(result.translation
                                                       - cell.mounting.position, axis))
            translation['ours'].append(error_mm)
            ratio.append(error_mm / result.translation_uncertainty_mm)
        ratios.append(ratio)
        for name, method in OPENCV_METHODS.items():
            answer = opencv(samples, method)
            if answer is None:
                failed[name] += 1
                continue
            q, t = answer
            rotation[name].append(np.degrees(quat.angle_between(q, cell.mounting.quaternion)))
            translation[name].append(1e3 * np.linalg.norm(determined(
                t - cell.mounting.position, axis)))
    honest = np.sqrt(np.mean(np.square(ratios), axis=0))
    for name in rotation:
        if not rotation[name]:
            print(f'| {kind} | {name} | NaN (all {cells}) | NaN | |')
            continue
        rms_deg = np.sqrt(np.mean(np.square(rotation[name])))
        rms_mm = (f'{np.sqrt(np.mean(np.square(translation[name]))):.2f}'
                  if translation[name] else '-')
        extra = (' / '.join(f'{v:.2f}' for v in honest) if name == 'ours' else '')
        nan = f' ({failed[name]} of {cells} NaN)' if failed[name] else ''
        print(f'| {kind} | {name} | {rms_deg:.3f}{nan} | {rms_mm} | {extra} |')


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--cells', type=int, default=20)
    args = parser.parse_args()
    print(f'{args.cells} cells per kind, 25 samples, 0.1 deg / 1 mm sensor noise\n')
    print('| robot | method | RMS rotation error (deg) | RMS determined translation error (mm) '
          '| ours: error / reported uncertainty (rotation / translation) |')
    print('|---|---|---|---|---|')
    for kind in simulation.REDUCED_KINDS:
        row(kind, args.cells)


if __name__ == '__main__':
    main()
