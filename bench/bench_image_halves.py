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
`--robot-deg` and `--robot-mm` (RMS per pose), as a real robot's are. With `--cells N`
(rendered only) the yardstick is the truth instead: the RMS error of each estimate over N
rendered folders, and over its RMS reported uncertainty (1 = honest).
Run: python bench/bench_image_halves.py [DIR] [--setup eye_to_hand] [--halves 40] [--seed 1]
     [--views 16] [--robot-deg 0.2] [--robot-mm 1] [--cells N]
"""

import argparse
import os
import tempfile

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import numpy as np  # noqa: E402

from quatcal_ros.core import quaternion as quat  # noqa: E402
from quatcal_ros.core.calibration import calibrate, CalibrationOptions  # noqa: E402
from quatcal_ros.sim.simulation import robot_reported  # noqa: E402
from quatcal_ros.vision.board import parse_board  # noqa: E402
from quatcal_ros.vision.camera import camera_from  # noqa: E402
from quatcal_ros.vision.dataset import load_image_dataset  # noqa: E402
from quatcal_ros.vision.render import cell_views, Renderer, write_dataset  # noqa: E402
from quatcal_ros.vision.reprojection import refine_from_poses  # noqa: E402

BOARD = {'type': 'charuco', 'squares_x': 7, 'squares_y': 5, 'square_length_m': 0.03,
         'marker_length_m': 0.022, 'dictionary': 'DICT_5X5_100'}


def rendered_folder(folder, views, robot_deg, robot_mm, rng):
    """
    Write a rendered eye-in-hand folder whose robot poses carry the robot's errors.

    Returns the true mounting.
    """
    camera = camera_from(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 'plumb_bob',
                         [0, 0, 0, 0, 0])
    renderer = Renderer(parse_board(BOARD), camera)
    mounting, _, seen, links = cell_views(rng, renderer, views, distance_m=(0.3, 0.8))
    images = [renderer.render(s, rng, noise=2.0, blur_sigma=0.6) for s in seen]
    write_dataset(folder, BOARD, camera, [f'view_{i:03d}.png' for i in range(views)],
                  robot_reported(rng, links, robot_deg, robot_mm), images)
    return mounting


def solve(data, picked, setup):
    """Return (pose-based CalibrationResult, ReprojectionFit) of the views `picked`."""
    samples = [data.samples[k] for k in picked]
    corners = data.corners()
    result = calibrate(samples, CalibrationOptions(setup=setup))
    return result, refine_from_poses(samples, [corners[k] for k in picked], data.camera,
                                     result, setup)


def off(estimate, quaternion, translation):
    """Return (deg, mm) of `estimate` from the mounting given, and its two uncertainties."""
    return (np.degrees(quat.angle_between(estimate.quaternion, quaternion)),
            1e3 * np.linalg.norm(estimate.translation - translation),
            estimate.uncertainty_deg, estimate.translation_uncertainty_mm)


def rendered(args, rng):
    """Return the ImageDataset of a rendered folder and its true mounting."""
    with tempfile.TemporaryDirectory() as scratch:
        truth = rendered_folder(scratch, args.views, args.robot_deg, args.robot_mm, rng)
        return load_image_dataset(scratch), truth


def halves_table(data, setup, halves, rng, source):
    """Print the half-sample yardstick of both estimates of one folder."""
    n = len(data.samples)
    whole = solve(data, range(n), setup)
    deviations = {'pixels': [], 'pose-based': []}
    sources = set()
    for _ in range(halves):
        half = solve(data, np.sort(rng.choice(n, n // 2, replace=False)), setup)
        sources.add(half[1].uncertainty_from)
        for name, estimate, full in zip(('pose-based', 'pixels'), half, whole):
            deviations[name].append(off(estimate, full.quaternion, full.translation))
    print(f'{source}: {n} views used ({len(data.refused)} refused), {halves} '
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


def truth_table(args, rng):
    """Print each estimate's RMS error over args.cells rendered folders, and over reported."""
    errors = {'pose-based': [], 'pixels': []}
    for _ in range(args.cells):
        data, truth = rendered(args, rng)
        for name, estimate in zip(errors, solve(data, range(len(data.samples)), 'eye_in_hand')):
            errors[name].append(off(estimate, truth.quaternion, truth.position))
    print(f'{args.cells} rendered folders of {args.views} views, the robot off by '
          f'{args.robot_deg:g} deg and {args.robot_mm:g} mm per pose')
    print('| estimate | RMS error (deg, mm) | RMS reported (deg, mm) | error / reported '
          '(rotation, translation) |')
    print('|---|---|---|---|')
    for name, rows in errors.items():
        rms = np.sqrt(np.mean(np.square(rows), axis=0))
        print(f'| {name} | {rms[0]:.3f}, {rms[1]:.2f} | {rms[2]:.3f}, {rms[3]:.2f} | '
              f'{rms[0] / rms[2]:.2f}, {rms[1] / rms[3]:.2f} |')


def main():
    """Print the table the arguments ask for."""
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
    parser.add_argument('--cells', type=int, default=0,
                        help='rendered folders for the error against the truth (no DIR)')
    args = parser.parse_args()
    if args.folder is not None and args.cells:
        parser.error('--cells renders its folders: give no DIR with it')
    if args.folder is None and args.setup != 'eye_in_hand':
        parser.error('a rendered folder is eye_in_hand: --setup applies to a DIR')
    rng = np.random.default_rng(args.seed)
    if args.cells and args.folder is None:
        return truth_table(args, rng)
    if args.folder is not None:
        return halves_table(load_image_dataset(args.folder), args.setup, args.halves, rng,
                            args.folder)
    return halves_table(rendered(args, rng)[0], 'eye_in_hand', args.halves, rng,
                        f'rendered, robot off by {args.robot_deg:g} deg and '
                        f'{args.robot_mm:g} mm per pose')


if __name__ == '__main__':
    main()
