#!/usr/bin/env python3
"""
Solver speed against issue 2's targets, beside OpenCV's PARK on the same samples.

- all-pairs least squares at 50 samples vs cv2.calibrateHandEye(PARK): target >= 3x faster;
- adding one sample to a 200-sample session and re-estimating by least squares: < 1 ms
  (the motion system alone); the live Calibrator's whole incremental update (estimate and
  quality figures) is shown beside it (the node's target: an estimate within 50 ms of its
  sample, 95th percentile, at 200 samples: bench_node.py);
- the full robust solve of 200 samples (10 % outliers): < 100 ms.
Run: python bench/bench_speed.py [--repeats N]
"""

import argparse
import time

import cv2
import numpy as np

from quatcal_ros.core.calibration import calibrate, CalibrationOptions, Calibrator
from quatcal_ros.core.leastsq import MotionSystem
from quatcal_ros.core.motions import Motions, pair_indices, SampleRotations
from quatcal_ros.sim import simulation


def median_ms(function, repeats):
    function()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return 1e3 * float(np.median(times))


def cell_samples(n, outliers=0.0, seed=1):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    return simulation.samples(rng, cell, n, rotation_noise_deg=0.5, translation_noise_m=0.001,
                              outlier_fraction=outliers)[0]


def park(samples):
    cv2.calibrateHandEye([s.link.rotation for s in samples],
                         [s.link.position.reshape(3, 1) for s in samples],
                         [s.sensor.rotation for s in samples],
                         [s.sensor.position.reshape(3, 1) for s in samples],
                         method=cv2.CALIB_HAND_EYE_PARK)


def add_one_to_motion_system(samples):
    """Least squares over 199 samples, then one more: time only the update and re-solve."""
    rotations = SampleRotations.from_samples(samples)
    n = len(samples) - 1
    system = MotionSystem()
    system.add(*_qs(Motions.between(rotations, *pair_indices(n))))

    def update():
        new = Motions.between(rotations, np.arange(n), np.full(n, n))
        copy = system.copy()
        copy.add(new.q_a, new.q_b)
        copy.solve()
    return update


def _qs(motions):
    return motions.q_a, motions.q_b


def add_one_to_calibrator(samples):
    """
    Time the live Calibrator's incremental path: the last sample added and estimated.

    Gate, motions, closed-form solve, refinement step and quality figures: what the node
    computes for each new sample between full solves.
    """
    calibrator = Calibrator(full_solve_every=10 ** 9)
    calibrator.add_samples(samples[:-1])
    calibrator.estimate()
    before = calibrator._solution

    def update():
        calibrator.add_sample(samples[-1])
        calibrator.estimate()
        calibrator.samples.pop()   # back to the estimate of the others, for the next repeat
        calibrator._solution, calibrator._estimated = before, len(calibrator.samples)
    return update


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument('--repeats', type=int, default=30)
    args = parser.parse_args()
    fifty = cell_samples(50)
    # Issue 2's targets are about the rotation solve: the closed form (Chou-Kamel least
    # squares with the closed-form translation), as PARK computes a rotation and translation.
    lsq = CalibrationOptions(robust=False, method='closed-form')
    ours = median_ms(lambda: calibrate(fifty, lsq), args.repeats)
    theirs = median_ms(lambda: park(fifty), args.repeats)
    two_hundred = cell_samples(200, outliers=0.1)
    refined = median_ms(lambda: calibrate(two_hundred), args.repeats)
    park_200 = median_ms(lambda: park(two_hundred), args.repeats)
    rows = [
        ('all-pairs least squares, 50 samples', ours, f'PARK {theirs:.2f} ms: '
         f'{theirs / ours:.1f}x faster (target >= 3x)'),
        ('add 1 sample to 200, motion system + solve',
         median_ms(add_one_to_motion_system(two_hundred), args.repeats), 'target < 1 ms'),
        ('add 1 sample to 200, live Calibrator update',
         median_ms(add_one_to_calibrator(two_hundred), args.repeats),
         'gating, closed form, refinement step, quality figures'),
        ('full robust solve, 200 samples, 10 % outliers',
         median_ms(lambda: calibrate(two_hundred, CalibrationOptions(method='closed-form')),
                   args.repeats), 'target < 100 ms'),
        ('full robust solve + joint refinement, 200 samples',
         refined, f'PARK {park_200:.2f} ms on the same samples (target: faster from 20 samples; '
         'bench_scaling.py has every size)'),
    ]
    print('| operation | median time (ms) | note |')
    print('|---|---|---|')
    for name, ms, note in rows:
        print(f'| {name} | {ms:.2f} | {note} |')


if __name__ == '__main__':
    main()
