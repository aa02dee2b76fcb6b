#!/usr/bin/env python3
"""
Solve time against the number of samples, ours beside OpenCV's calibrateHandEye in one run.

Every row solves the same synthetic eye-in-hand samples (0.5 deg, 1 mm sensor noise): ours by
default (refined + robust), closed form (robust) and plain least squares (closed form,
--no-robust), and OpenCV's PARK, TSAI and HORAUD (O(N^2) in the motions it forms: skipped
above --opencv-max samples). Times are CPU milliseconds per solve (process time, median of
--repeats), single-threaded BLAS as the tools run it, averaged over --cells cells (different
robots, mountings and noise draws: a cell can cost more, e.g. when its fit looks poor enough
for the frame-convention check) up to 200 samples and one cell above; every method runs on
the same cell before the next cell. 'LSQ rotation kernel' is the O(N) all-pairs
least-squares rotation alone (the floor the estimates build on).

Printed after the table: the growth exponent of each of ours from 100 to the largest N
(time ~ N^k) and the load average; with --memory the peak resident memory of a solve of
10,000 and 100,000 samples in a fresh process; with --startup the wall time of
`python -m quatcal_ros solve` on a 20-row CSV beside bench/opencv_solve_csv.py (csv, numpy and
cv2 only) on the same file.
With --recordings, also the default solve on the two real recordings in data/ (as
bench_honesty.py reads them) beside OpenCV's methods given the same poses in OpenCV's
convention, with each OpenCV answer's angle from ours (so the two solved the same problem);
each whole and as 20 evenly spaced samples of it.
Run: python bench/bench_scaling.py [--repeats 5] [--cells 5] [--sizes 10 20 ...] [--memory]
[--startup] [--recordings]
"""

import argparse
import itertools
import os
import subprocess
import sys
import tempfile
import time

# One BLAS thread, as the tools run (quatcal_ros.core.threads): set before numpy loads.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

from bench_honesty import angle_deg, RECORDINGS  # noqa: E402, I100 (the same real samples)
from bench_speed import cell_samples  # noqa: E402, I100 (the same cells)
import cv2  # noqa: E402, I100
import numpy as np  # noqa: E402

from quatcal_ros.core import quaternion as quat  # noqa: E402
from quatcal_ros.core.calibration import calibrate, CalibrationOptions  # noqa: E402
from quatcal_ros.core.leastsq import all_pairs_rotation  # noqa: E402
from quatcal_ros.core.motions import SampleRotations  # noqa: E402
from quatcal_ros.files.samples_csv import format_samples  # noqa: E402

OURS = {
    'ours default': CalibrationOptions(),
    'ours closed-form': CalibrationOptions(method='closed-form'),
    'ours LSQ': CalibrationOptions(method='closed-form', robust=False),
}
# The O(N) all-pairs least-squares rotation alone (leastsq.all_pairs_rotation): the floor.
KERNEL = 'LSQ rotation kernel'
OPENCV = {'PARK': cv2.CALIB_HAND_EYE_PARK, 'TSAI': cv2.CALIB_HAND_EYE_TSAI,
          'HORAUD': cv2.CALIB_HAND_EYE_HORAUD}


def cpu_ms(function, repeats):
    function()
    times = []
    for _ in range(repeats):
        start = time.process_time()
        function()
        times.append(time.process_time() - start)
    return 1e3 * float(np.median(times))


def opencv_arguments(samples, setup='eye_in_hand', invert_sensor=False):
    """
    Return calibrateHandEye's four lists for our samples under a setup and sensor direction.

    OpenCV takes the gripper in the base and the target in the camera: eye-to-hand passes the
    base in the gripper instead (its documented use), inverted sensor poses are inverted back.
    """
    links = [s.link if setup == 'eye_in_hand' else s.link.inverse() for s in samples]
    sensors = [s.sensor.inverse() if invert_sensor else s.sensor for s in samples]
    return ([p.rotation for p in links], [p.position.reshape(3, 1) for p in links],
            [p.rotation for p in sensors], [p.position.reshape(3, 1) for p in sensors])


def opencv_solver(samples, method, **convention):
    """Return a call of calibrateHandEye on `samples` (opencv_arguments collected first)."""
    arguments = opencv_arguments(samples, **convention)
    return lambda: cv2.calibrateHandEye(*arguments, method=method)


def recordings_table(repeats):
    """Print the default solve on the real recordings beside OpenCV's methods."""
    print('| recording | samples | ours default | ' + ' | '.join(OPENCV) +
          ' | default / PARK | default / best OpenCV | OpenCV angle from ours (deg) |')
    print('|---' * (len(OPENCV) + 6) + '|')
    for (name, (load, extra)), size in itertools.product(RECORDINGS.items(), (None, 20)):
        samples = load()
        if size is not None:   # evenly spaced, as a short session of the same cell
            samples = [samples[k] for k in np.linspace(0, len(samples) - 1, size, dtype=int)]
        options = CalibrationOptions(**extra)
        ours = cpu_ms(lambda: calibrate(samples, options), repeats)
        ours_rotation = calibrate(samples, options).quaternion
        times, angles = {}, {}
        for method, flag in OPENCV.items():
            solver = opencv_solver(samples, flag, **extra)
            times[method] = cpu_ms(solver, repeats)
            angles[method] = angle_deg(quat.quaternion_from_matrix(solver()[0]), ours_rotation)
        best = min(times.values())
        print(f'| {name} | {len(samples)} | {ours:.2f} | '
              + ' | '.join(f'{times[m]:.2f}' for m in OPENCV)
              + f' | {ours / times["PARK"]:.2f} | {ours / best:.2f} | '
              + ', '.join(f'{m} {angles[m]:.2f}' for m in OPENCV) + ' |')


def kernel(samples):
    """Return a call of the O(N) least squares on `samples` (rotations collected first)."""
    rotations = SampleRotations.from_samples(samples)
    use = np.ones(len(samples), dtype=bool)
    reference = calibrate(samples, OURS['ours LSQ']).closed_form.quaternion
    return lambda: all_pairs_rotation(rotations, use, reference)


def peak_memory(n):
    """
    Return (CPU s, peak RSS MB) of one default solve of n samples in a fresh process.

    The peak is the child's VmHWM (its own address space's high-water mark): ru_maxrss would
    carry this process's peak over the fork.
    """
    code = ('import time, sys; sys.path.insert(0, %r); import bench_scaling as b; '
            's = b.cell_samples(%d); t = time.process_time(); b.calibrate(s); '
            'hwm = [l for l in open("/proc/self/status") if l.startswith("VmHWM")][0]; '
            'print(time.process_time() - t, int(hwm.split()[1]) / 1024)'
            % (os.path.dirname(os.path.abspath(__file__)), n))
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         check=True).stdout.split()
    return float(out[0]), float(out[1])


def startup(repeats):
    """Return median wall seconds of `solve` and of the OpenCV script on a 20-row CSV."""
    here = os.path.dirname(os.path.abspath(__file__))
    with tempfile.TemporaryDirectory() as folder:
        path = os.path.join(folder, 'samples.csv')
        with open(path, 'w') as stream:
            stream.write(format_samples(cell_samples(20)))
        commands = {'solve': [sys.executable, '-m', 'quatcal_ros', 'solve', path],
                    'opencv': [sys.executable, os.path.join(here, 'opencv_solve_csv.py'),
                               path]}
        times = {name: [] for name in commands}
        for _ in range(repeats):
            for name, command in commands.items():
                start = time.perf_counter()
                subprocess.run(command, check=True, stdout=subprocess.DEVNULL,
                               cwd=os.path.dirname(here))
                times[name].append(time.perf_counter() - start)
    return {name: float(np.median(values)) for name, values in times.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--repeats', type=int, default=5)
    parser.add_argument('--cells', type=int, default=5)
    parser.add_argument('--sizes', type=int, nargs='+',
                        default=[10, 20, 50, 100, 200, 1000, 2000, 10000])
    parser.add_argument('--opencv-max', type=int, default=2000)
    parser.add_argument('--memory', action='store_true')
    parser.add_argument('--startup', action='store_true')
    parser.add_argument('--recordings', action='store_true')
    args = parser.parse_args()
    if args.recordings:
        recordings_table(args.repeats)
    if args.startup:
        ours, opencv = (startup(args.repeats)[name] for name in ('solve', 'opencv'))
        print(f'solve on a 20-row CSV: {ours:.2f} s wall; the OpenCV script: {opencv:.2f} s; '
              f'ratio {ours / opencv:.2f} (median of {args.repeats})')
    names = list(OURS) + [KERNEL] + list(OPENCV)
    print('| N | ' + ' | '.join(names) + ' | default / PARK | default / best OpenCV |')
    print('|---' * (len(names) + 3) + '|')
    ours_times = {name: [] for name in OURS}
    for n in args.sizes:
        cells = args.cells if n <= 200 else 1
        row = dict.fromkeys(names, 0.0)
        for seed in range(1, cells + 1):
            samples = cell_samples(n, seed=seed)
            for name, options in OURS.items():
                row[name] += cpu_ms(lambda: calibrate(samples, options), args.repeats) / cells
            row[KERNEL] += cpu_ms(kernel(samples), args.repeats) / cells
            for name, method in OPENCV.items():
                row[name] += (cpu_ms(opencv_solver(samples, method), args.repeats) / cells
                              if n <= args.opencv_max else float('nan'))
        for name in OURS:
            ours_times[name].append(row[name])
        best = min(row[name] for name in OPENCV)
        cells = [f'{row[name]:.2f}' if np.isfinite(row[name]) else '-' for name in names]
        ratios = [f'{row["ours default"] / row["PARK"]:.2f}' if np.isfinite(row['PARK'])
                  else '-', f'{row["ours default"] / best:.2f}' if np.isfinite(best) else '-']
        print(f'| {n} | ' + ' | '.join(cells + ratios) + ' |')
    sizes = np.array(args.sizes, dtype=float)
    big = sizes >= 100
    if np.sum(big) >= 2:
        for name, times in ours_times.items():
            k = np.polyfit(np.log(sizes[big]), np.log(np.array(times)[big]), 1)[0]
            print(f'growth exponent of {name} from {int(sizes[big][0])} to '
                  f'{int(sizes[big][-1])} samples: {k:.2f}')
    print(f'load average: {" ".join(f"{v:.1f}" for v in os.getloadavg())}; CPU ms per solve')
    if args.memory:
        for n in (10000, 100000):
            cpu, rss = peak_memory(n)
            print(f'{n} samples, default solve in a fresh process: {cpu:.2f} s CPU, '
                  f'peak RSS {rss:.0f} MB (whole process, samples included)')


if __name__ == '__main__':
    main()
