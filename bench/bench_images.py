#!/usr/bin/env python3
"""
Camera images: accuracy on rendered views beside OpenCV, and detection throughput.

The estimate on the pixels beside the pose-based ones and OpenCV's five calibrateHandEye
methods fed by the same detections.

Each trial renders a ChArUco board (7 x 5 squares of 30 mm) from a known camera (640 x 480,
f = 600 px) at 0.3-0.9 m, with 2 grey levels of image noise and a slight blur
(vision/render.py), detects it (vision/detect.py: corners, planar PnP, covariance), and
solves: ours on the pixels (`solve DIR`'s refinement; and without the views' shared errors,
every corner counted as independent, as before they were fitted), ours pose-based (the
refined default, each view weighed by its PnP covariance), and cv2.calibrateHandEye's TSAI,
PARK, HORAUD, ANDREFF and DANIILIDIS on the same PnP poses. RMS errors against the truth
over the trials. With --robot-deg D --robot-mm M every method is given the link poses a
robot reports, each off by D deg and M mm RMS (the images are rendered from the true ones),
as on a real cell. With --focal-error P camera_info's focal lengths are given P % too long
(the images rendered with the true ones): every method gets the detections made with them, and
ours on the pixels fits their scale when the corners show it ("with camera_info's focal
lengths" beside it keeps them). The CPU time of our default fit on the pixels is in each row
of the views' table (ms per cell).
Throughput: detection of one view (corners, PnP, checks) per second at 640 x 480 and 1920 x
1080, single-threaded BLAS.
Run: python bench/bench_images.py [--trials 10] [--views 10 20 50] [--robot-deg 0.2]
     [--robot-mm 1] [--focal-error 2] [--no-throughput]
"""

import argparse
import os
import time

os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

import cv2  # noqa: E402, I100
import numpy as np  # noqa: E402

from quatcal_ros.core import quaternion as quat  # noqa: E402
from quatcal_ros.core.calibration import calibrate  # noqa: E402
from quatcal_ros.core.pose import Sample  # noqa: E402
from quatcal_ros.sim.simulation import robot_reported  # noqa: E402
from quatcal_ros.vision.board import parse_board  # noqa: E402
from quatcal_ros.vision.camera import camera_from  # noqa: E402
from quatcal_ros.vision.detect import detect  # noqa: E402
from quatcal_ros.vision.render import cell_views, Renderer, view_poses  # noqa: E402
from quatcal_ros.vision.reprojection import refine_from_poses, with_focal_scale  # noqa: E402

BOARD = {'type': 'charuco', 'squares_x': 7, 'squares_y': 5, 'square_length_m': 0.03,
         'marker_length_m': 0.022, 'dictionary': 'DICT_5X5_100'}
OPENCV = {'TSAI': cv2.CALIB_HAND_EYE_TSAI, 'PARK': cv2.CALIB_HAND_EYE_PARK,
          'HORAUD': cv2.CALIB_HAND_EYE_HORAUD, 'ANDREFF': cv2.CALIB_HAND_EYE_ANDREFF,
          'DANIILIDIS': cv2.CALIB_HAND_EYE_DANIILIDIS}


def camera(width=640, height=480, f=600.0):
    return camera_from(width, height, [[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]],
                       'plumb_bob', [0, 0, 0, 0, 0])


def trial(renderer, views, seed, robot_deg=0.0, robot_mm=0.0, focal_error=0.0):
    """
    Return {method: (rotation error deg, translation error mm)} of one rendered cell.

    And the views found, and the CPU seconds of our default fit on the pixels.
    """
    rng = np.random.default_rng(seed)
    X, _, seen_poses, cell_links = cell_views(rng, renderer, views)
    told = with_focal_scale(renderer.camera, 1.0 + focal_error / 100.0)   # camera_info's
    links, found = [], []
    for seen, link in zip(seen_poses, cell_links):
        view = detect(renderer.render(seen, rng, noise=2.0, blur_sigma=0.6), renderer.board,
                      told)
        if view.ok:
            links.append(link)
            found.append(view)
    if links and (robot_deg or robot_mm):   # what the robot reports: each pose off (RMS)
        links = robot_reported(rng, links, robot_deg, robot_mm)
    samples = [Sample(i * 10 ** 9, link, view.pose)
               for i, (link, view) in enumerate(zip(links, found))]
    estimates = {}
    pose_based = calibrate(samples)
    estimates['ours, pose-based (refined, PnP covariances)'] = (
        pose_based.quaternion, pose_based.translation)
    corners = [(v.object_points, v.image_points) for v in found]
    start = time.process_time()
    fit = refine_from_poses(samples, corners, told, pose_based)
    cost = time.process_time() - start
    estimates['ours, on the pixels (reprojection)'] = (fit.quaternion, fit.translation)
    kept = refine_from_poses(samples, corners, told, pose_based, focal=False)
    estimates["ours, on the pixels, with camera_info's focal lengths"] = (
        kept.quaternion, kept.translation)
    plain = refine_from_poses(samples, corners, told, pose_based, view_errors=False,
                              focal=False)
    estimates["ours, on the pixels, without the views' shared errors"] = (
        plain.quaternion, plain.translation)
    for name, method in OPENCV.items():
        R, t = cv2.calibrateHandEye([link.rotation for link in links],
                                    [link.position.reshape(3, 1) for link in links],
                                    [v.pose.rotation for v in found],
                                    [v.pose.position.reshape(3, 1) for v in found],
                                    method=method)
        estimates[f'OpenCV {name}'] = (quat.quaternion_from_matrix(R), t.ravel())
    return {name: (np.degrees(quat.angle_between(q, X.quaternion)),
                   1e3 * np.linalg.norm(t - X.position))
            for name, (q, t) in estimates.items()}, len(found), cost


def throughput(width, height, repeats=20):
    cam = camera(width, height, f=600.0 * width / 640)
    renderer = Renderer(parse_board(BOARD), cam)
    rng = np.random.default_rng(1)
    images = [renderer.render(pose, rng, noise=2.0, blur_sigma=0.6)
              for pose in view_poses(rng, repeats, renderer)]
    start = time.process_time()
    ok = sum(detect(image, renderer.board, cam).ok for image in images)
    return repeats / (time.process_time() - start), ok


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--trials', type=int, default=10)
    parser.add_argument('--views', type=int, nargs='+', default=[10, 20, 50])
    parser.add_argument('--robot-deg', type=float, default=0.0)
    parser.add_argument('--robot-mm', type=float, default=0.0)
    parser.add_argument('--focal-error', type=float, default=0.0,
                        help="camera_info's focal lengths this many percent too long")
    parser.add_argument('--no-throughput', action='store_true')
    args = parser.parse_args()
    if args.robot_deg or args.robot_mm:
        print(f'(the link poses off by {args.robot_deg:g} deg and {args.robot_mm:g} mm RMS '
              'per pose)')
    if args.focal_error:
        print(f"(camera_info's focal lengths {args.focal_error:g} % too long)")
    renderer = Renderer(parse_board(BOARD), camera())
    print('| views | method | RMS rotation error (deg) | RMS translation error (mm) |')
    print('|---|---|---|---|')
    for views in args.views:
        errors, used, costs = {}, [], []
        for k in range(args.trials):
            found, count, cost = trial(renderer, views, 1000 * views + k, args.robot_deg,
                                       args.robot_mm, args.focal_error)
            used.append(count)
            costs.append(cost)
            for name, pair in found.items():
                errors.setdefault(name, []).append(pair)
        for name, pairs in errors.items():
            pairs = np.array(pairs)
            rms = np.sqrt(np.mean(pairs ** 2, axis=0))
            print(f'| {views} | {name} | {rms[0]:.4f} | {rms[1]:.3f} |')
        print(f'| {views} | (CPU of our default fit on the pixels: {1e3 * np.mean(costs):.0f} ms '
              f'mean, {1e3 * np.max(costs):.0f} ms most) | | |')
    print(f'({args.trials} rendered cells per row)')
    if args.no_throughput:
        return
    print()
    print('| image size | views detected per second (CPU) | views found |')
    print('|---|---|---|')
    for width, height in ((640, 480), (1920, 1080)):
        rate, ok = throughput(width, height)
        print(f'| {width} x {height} | {rate:.1f} | {ok} of 20 |')


if __name__ == '__main__':
    main()
