#!/usr/bin/env python3
"""
Session size: `solve` on 10,000 and 100,000 samples, and resuming a 10,000-sample journal.

Each row is a fresh process, timed from outside (wall seconds) with its peak resident memory
(ru_maxrss of the child): `python -m quatcal_ros solve FILE.csv` on a samples CSV of N
synthetic eye-in-hand samples (0.5 deg, 1 mm), and what the calibrator does on start with
resume:=true (open the journal with resume, add its samples to the session, estimate), in a
process that imports what the node's core imports (no DDS). Targets of the reliability
issue: 10,000 samples in under 2 s and 300 MB, 100,000 in under 30 s, resume of 10,000 in
under 5 s.
Run: python bench/bench_size.py [--sizes 10000 100000] [--resume 10000]
"""

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np

from quatcal_ros.files.journal import JournalHeader, start
from quatcal_ros.files.samples_csv import format_samples
from quatcal_ros.sim import simulation

RESUME = """
import sys
from quatcal_ros.files.session_record import SamplesJournal
from quatcal_ros.files.journal import JournalHeader
from quatcal_ros.stream.session import Session
journal = SamplesJournal(sys.argv[1], JournalHeader('eye_in_hand', 'tool0', 'camera'), True)
session = Session()
session.add_samples(journal.report.samples)
session.estimate()
assert session.result is not None and session.result.samples == int(sys.argv[2])
"""


def samples(n, seed=1):
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    return simulation.samples(rng, cell, n, rotation_noise_deg=0.5,
                              translation_noise_m=0.001)[0]


def run(command):
    """Return (wall s, peak RSS MB) of a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    start_s = time.perf_counter()
    subprocess.run(command, check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start_s
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    return wall, max(peak, before) / 1024


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument('--sizes', type=int, nargs='+', default=[10000, 100000])
    parser.add_argument('--resume', type=int, default=10000)
    args = parser.parse_args()
    print('| what | samples | wall s | peak RSS MB | target |')
    print('|---|---|---|---|---|')
    targets = {10000: '< 2 s, < 300 MB', 100000: '< 30 s'}
    with tempfile.TemporaryDirectory() as folder:
        for n in sorted(args.sizes):   # peak RSS of children only grows: smallest first
            path = os.path.join(folder, f'samples_{n}.csv')
            with open(path, 'w') as stream:
                stream.write(format_samples(samples(n)))
            wall, peak = run([sys.executable, '-m', 'quatcal_ros', 'solve', path])
            print(f'| `solve` | {n} | {wall:.2f} | {peak:.0f} | {targets.get(n, "")} |')
        path = os.path.join(folder, 'journal.csv')
        journal, _ = start(path, JournalHeader('eye_in_hand', 'tool0', 'camera'), False)
        for sample in samples(args.resume):
            journal.append(sample, sync=False)
        journal.sync()
        journal.close()
        wall, peak = run([sys.executable, '-c', RESUME, path, str(args.resume)])
        print(f'| resume (journal + session + estimate) | {args.resume} | {wall:.2f} | '
              f'{peak:.0f} | < 5 s |')
    print(f'load average: {" ".join(f"{v:.1f}" for v in os.getloadavg())}; the peak RSS of '
          'each row is the largest of it and the rows before it (ru_maxrss of children)')


if __name__ == '__main__':
    main()
