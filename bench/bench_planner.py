#!/usr/bin/env python3
"""
The next-pose planner: samples needed to reach an uncertainty, following it or not.

Each cell (simulation.random_cell, 0.3 deg / 2 mm sensor noise) starts from 4 random still
samples; then each next sample is taken at the planner's proposal (core/planner.py), or, for
the baseline, at a random one of the same candidates (the same limits: target in view,
within 45 deg of the last link orientation, in the workspace box). After each sample the
default estimate is computed; the count is the first sample at which its reported uncertainty
is below the targets (rotation and translation), at most --max-samples.
Run: python bench/bench_planner.py [--cells 50] [--target-deg 0.1] [--target-mm 2]
"""

import argparse
from dataclasses import replace
import os

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from quatcal_ros.core.calibration import calibrate  # noqa: E402
from quatcal_ros.core.planner import plan_next_pose, PlanLimits  # noqa: E402
from quatcal_ros.core.pose import Pose, Sample  # noqa: E402
from quatcal_ros.core.solver import DegenerateMotionError  # noqa: E402
from quatcal_ros.sim import simulation  # noqa: E402

NOISE = {'rotation_noise_deg': 0.3, 'translation_noise_m': 0.002}


def observe(rng, cell, link, index):
    """Return the still sample a noisy sensor gives at link pose `link`."""
    p, q = cell.sensor_poses(link.position[None], link.quaternion[None])
    p, q = simulation.add_pose_noise(rng, p, q, NOISE['rotation_noise_deg'],
                                     NOISE['translation_noise_m'])
    return Sample(index * 2_000_000_000, link, Pose(p[0], q[0]))


def session(seed, follow, targets, max_samples):
    """Return the samples taken until the reported uncertainty meets the targets."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    samples = simulation.samples(rng, cell, 4, **NOISE)[0]
    choose = np.random.default_rng(seed + 1)
    while len(samples) < max_samples:
        try:
            result = calibrate(samples)
        except DegenerateMotionError:
            result = None
        if result is not None and result.uncertainty_deg <= targets[0] \
                and result.translation_uncertainty_mm <= targets[1]:
            return len(samples)
        limits = PlanLimits(seed=int(choose.integers(2 ** 31)))
        if follow:
            proposal = plan_next_pose(samples, result, limits=limits)
            link = proposal.link if proposal is not None else None
        else:
            link = random_candidate(samples, result, limits, choose)
        if link is None:
            link = simulation.stop_poses(rng, cell, 1)[0]
        samples.append(observe(rng, cell, link, len(samples)))
    return max_samples


def random_candidate(samples, result, limits, rng):
    """Return a random link pose among the planner's candidates that the limits allow."""
    one = replace(limits, candidates=1)
    for _ in range(200):
        proposal = plan_next_pose(samples, result, limits=replace(
            one, seed=int(rng.integers(2 ** 31))))
        if proposal is not None:
            return proposal.link
    return None


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--cells', type=int, default=50)
    parser.add_argument('--target-deg', type=float, default=0.1)
    parser.add_argument('--target-mm', type=float, default=2.0)
    parser.add_argument('--max-samples', type=int, default=80)
    args = parser.parse_args()
    targets = (args.target_deg, args.target_mm)
    counts = {follow: [session(1000 + k, follow, targets, args.max_samples)
                       for k in range(args.cells)] for follow in (True, False)}
    planned, random = np.array(counts[True]), np.array(counts[False])
    print(f'| poses | samples to reach {args.target_deg:g} deg and {args.target_mm:g} mm '
          f'(median) | mean | 90th pct | capped at {args.max_samples} |')
    print('|---|---|---|---|---|')
    for name, values in (("the planner's", planned), ('random, same limits', random)):
        print(f'| {name} | {np.median(values):.0f} | {values.mean():.1f} | '
              f'{np.percentile(values, 90):.0f} | {int(np.sum(values >= args.max_samples))} |')
    print(f'\nratio of the means: {planned.mean() / random.mean():.2f} '
          f'(target at most 0.6); {args.cells} cells, 4 random samples to start')


if __name__ == '__main__':
    main()
