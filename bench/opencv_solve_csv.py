#!/usr/bin/env python3
"""
Solve a samples CSV with OpenCV's calibrateHandEye (PARK): the start-up yardstick of `solve`.

The equivalent of `python -m quatcal_ros solve FILE.csv` in the fewest imports: csv, numpy,
cv2. bench_scaling.py --startup times both as whole processes.
Run: python bench/opencv_solve_csv.py SAMPLES.csv
"""

import csv
import sys

import cv2
import numpy as np


def matrix(row, prefix):
    """Return the rotation matrix of the quaternion columns of `prefix` (x, y, z, w)."""
    x, y, z, w = (float(row[prefix + k]) for k in ('qx', 'qy', 'qz', 'qw'))
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def column(row, prefix):
    """Return the position columns of `prefix` as a 3x1 array."""
    return np.array([[float(row[prefix + k])] for k in ('x', 'y', 'z')])


def main():
    with open(sys.argv[1], newline='') as stream:
        rows = list(csv.DictReader(stream))
    rotation, translation = cv2.calibrateHandEye(
        [matrix(r, 'link_') for r in rows], [column(r, 'link_') for r in rows],
        [matrix(r, 'sensor_') for r in rows], [column(r, 'sensor_') for r in rows],
        method=cv2.CALIB_HAND_EYE_PARK)
    print(rotation.tolist(), translation.ravel().tolist())


if __name__ == '__main__':
    main()
