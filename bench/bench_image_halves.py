#!/usr/bin/env python3
"""
Check that the uncertainty of `solve DIR` is honest on a real folder of camera images.

The half-sample yardstick of bench_honesty.py on an image folder (the layout `solve DIR`
reads): the RMS deviation of `--halves` random half-folder estimates from the whole folder's,
divided by the halves' own reported uncertainty times sqrt(1/2) (1 = honest), for the
estimate on the pixels (`solve DIR`'s published one) and the pose-based one beside it. The
boards are detected once; each half is solved as `solve DIR` solves (pose-based default, then
the fit on the pixels of the views it used). Without DIR, a rendered eye-in-hand folder
(`--views` views of a ChArUco board, 640 x 480, f = 600 px) whose robot poses are off by
`--robot-deg` and `--robot-mm` (RMS per pose), as a real robot's are.
Run: python bench/bench_image_halves.py [DIR] [--setup eye_to_hand] [--halves 40] [--seed 1]
     [--views 16] [--robot-deg 0.2] [--robot-mm 1]
"""

import argparse
import os
import tempfile

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from quatcal_ros.core import quaternion as quat  # noqa: E402
from quatcal_ros.core.calibration import calibrate, CalibrationOptions  # noqa: E402
from quatcal_ros.core.pose import Pose  # noqa: E402
from quatcal_ros.vision.board import parse_board  # noqa: E402
from quatcal_ros.vision.camera import camera_from  # noqa: E402
from quatcal_ros.vision.dataset import load_image_dataset  # noqa: E402
from quatcal_ros.vision.render import cell_views, Renderer, write_dataset  # noqa: E402
from quatcal_ros.vision.reprojection import refine_from_poses  # noqa: E402

BOARD = {'type': 'charuco', 'squares_x': 7, 'squares_y': 5, 'square_length_m': 0.03,
         'marker_length_m': 0.022, 'dictionary': 'DICT_5X5_100'}


def rendered_folder(folder, views, robot_deg, robot_mm, rng):
    """Write a rendered eye-in-hand folder whose robot poses carry the robot's errors."""
    camera = camera_from(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 'plumb_bob',
                         [0, 0, 0, 0, 0])
    renderer = Renderer(parse_board(BOARD), camera)
    _, _, seen, links = cell_views(rng, renderer, views, distance_m=(0.3, 0.8))
    images = [renderer.render(s, rng, noise=2.0, blur_sigma=0.6) for s in seen]
    reported = [Pose(link.position + rng.normal(0.0, 1e-3 * robot_mm / np.sqrt(3.0), 3),
                     quat.multiply(quat.from_rotation_vector(
                         rng.normal(0.0, np.radians(robot_deg) / np.sqrt(3.0), 3)),
                         link.quaternion)) for link in links]
    write_dataset(folder, BOARD, camera, [f'view_{i:03d}.png' for i in range(views)],
                  reported, images)


def solve(data, picked, setup):
    """Return (pose-based CalibrationResult, ReprojectionFit) of the views `picked`."""
    samples = [data.samples[k] for k in picked]
    corners = data.corners()
    result = calibrate(samples, CalibrationOptions(setup=setup))
    return result, refine_from_poses(samples, [corners[k] for k in picked], data.camera,
                                     result, setup)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('folder', nargs='?',
                        help='an image folder as `solve DIR` reads it (default: rendered)')
    parser.add_argument('--setup', choices=('eye_in_hand', 'eye_to_hand'),
                        default='eye_in_hand')
    parser.add_argument('--halves', type=int, default=40)
    parser.add_argument('--seed', type=int, default=1)
    parser.add_argument('--views', type=int, default=16)
    parser.add_argument('--robot-deg', type=float, default=0.2)
    parser.add_argument('--robot-mm', type=float, default=1.0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    with tempfile.TemporaryDirectory() as scratch:
        if args.folder is None:
            rendered_folder(scratch, args.views, args.robot_deg, args.robot_mm, rng)
            args.setup = 'eye_in_hand'
        data = load_image_dataset(args.folder or scratch)
    source = args.folder or (f'rendered, robot off by {args.robot_deg:g} deg and '
                             f'{args.robot_mm:g} mm per pose')
    n = len(data.samples)
    whole = solve(data, range(n), args.setup)
    deviations = {'pixels': [], 'pose-based': []}
    sources = set()
    for _ in range(args.halves):
        half = solve(data, np.sort(rng.choice(n, n // 2, replace=False)), args.setup)
        sources.add('view_blocks' if half[1].resampled is not None else 'model')
        for name, estimate, full in zip(('pose-based', 'pixels'), half, whole):
            deviations[name].append((
                np.degrees(quat.angle_between(estimate.quaternion, full.quaternion)),
                1e3 * np.linalg.norm(estimate.translation - full.translation),
                estimate.uncertainty_deg, estimate.translation_uncertainty_mm))
    print(f'{source}: {n} views used ({len(data.refused)} refused), {args.halves} '
          f'halves of {n // 2}; pixel uncertainty of the halves from {", ".join(sorted(sources))}')
    print('| estimate | whole: uncertainty (deg, mm) | halves: RMS deviation (deg, mm) | '
          'halves: RMS reported (deg, mm) | ratio rotation | ratio translation |')
    print('|---|---|---|---|---|---|')
    for name, full in zip(('pose-based', 'pixels'), whole):
        rms = np.sqrt(np.mean(np.square(deviations[name]), axis=0))
        ratio = rms[:2] / (rms[2:] * np.sqrt(0.5))
        print(f'| {name} | {full.uncertainty_deg:.3f}, {full.translation_uncertainty_mm:.2f} | '
              f'{rms[0]:.3f}, {rms[1]:.2f} | {rms[2]:.3f}, {rms[3]:.2f} | {ratio[0]:.2f} | '
              f'{ratio[1]:.2f} |')


if __name__ == '__main__':
    main()
