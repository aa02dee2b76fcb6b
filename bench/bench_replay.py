#!/usr/bin/env python3
"""
Offline replay speed: `replay` beside rosbags alone reading and deserialising the same bag.

Writes (to a temporary directory) a simulated stop-and-go recording, by default 10 minutes
with a 1 kHz link stream (geometry_msgs/PoseStamped) and a 30 Hz sensor stream, in each
storage format; then times, best of --repeats runs:
- bare read: rosbags' Reader over every message, each deserialised (the floor);
- replay: cli.replay_main on the bag (read, convert, pair, capture, estimate, final solve).
Target: the replay runs at no less than half the bare read rate.  --profile prints the
replay's cProfile (top functions by own time).  --processes instead runs both as whole
processes (`python -m quatcal_ros replay` against a script that only reads and deserialises,
imports included) and prints their CPU seconds and peak resident memory: the targets are CPU
within 1.1x of the bare read's and peak memory flat in bag length (<= 1.5x the bare read's).
--estimate-time-offset runs the replay with it (it holds both streams whole: no flat target).
Run: python bench/bench_replay.py [--minutes M] [--storage sqlite3 mcap] [--profile]
                                  [--processes [--estimate-time-offset]]
"""

import argparse
import contextlib
import cProfile
import io
import pstats
import tempfile
import time

import numpy as np

from quatcal_ros.ros import conversions
from quatcal_ros.ros.bag import TYPESTORE, write_bag
from quatcal_ros.sim import simulation
from quatcal_ros.tools.cli import replay_main

LINK_RATE_HZ = 1000.0
SENSOR_RATE_HZ = 30.0
STILL_S, MOVE_S = 1.5, 2.0
TOPICS = {'/link_pose': 'geometry_msgs/msg/PoseStamped',
          '/sensor_pose': 'geometry_msgs/msg/PoseStamped'}


def recording(minutes, seed=7):
    """Return (log-time ordered messages, the cell) of a stop-and-go run of `minutes`."""
    rng = np.random.default_rng(seed)
    cell = simulation.random_cell(rng)
    stops = int(minutes * 60 / (STILL_S + MOVE_S)) + 1
    streams = simulation.stop_and_go_streams(
        rng, cell, stops, link_rate_hz=LINK_RATE_HZ, sensor_rate_hz=SENSOR_RATE_HZ,
        still_s=STILL_S, move_s=MOVE_S, rotation_noise_deg=0.2, translation_noise_m=0.001)
    messages = [('/link_pose', stamp + 500_000,
                 conversions.pose_stamped_msg(pose, stamp, 'base', typestore=TYPESTORE))
                for stamp, pose in streams.link]
    messages += [('/sensor_pose', delivered,
                  conversions.pose_stamped_msg(pose, stamp, 'camera', typestore=TYPESTORE))
                 for (stamp, pose), delivered in zip(streams.sensor, streams.sensor_delivery_ns)]
    messages.sort(key=lambda message: message[1])
    return messages, cell


def bare_read(path):
    """Read and deserialise every message with rosbags alone; return the count."""
    from rosbags.rosbag2 import Reader
    count = 0
    with Reader(path) as reader:
        for connection, _, raw in reader.messages():
            TYPESTORE.deserialize_cdr(raw, connection.msgtype)
            count += 1
    return count


def replay(path):
    """Run `replay` as the command line does (quiet); return the result's JSON text."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        status = replay_main([str(path), '--link-topic', '/link_pose',
                              '--sensor-topic', '/sensor_pose', '--quiet'])
    if status != 0:
        raise SystemExit(f'replay failed with exit status {status}')
    return out.getvalue()


BARE_READ = """
import sys
from rosbags.rosbag2 import Reader
from rosbags.typesys import get_typestore, Stores
store = get_typestore(Stores.ROS2_JAZZY)
with Reader(sys.argv[1]) as reader:
    for connection, _, raw in reader.messages():
        store.deserialize_cdr(raw, connection.msgtype)
"""


def process_cost(command):
    """Return (CPU s, peak RSS MB) of a child process, measured by GNU time."""
    import subprocess
    done = subprocess.run(['/usr/bin/time', '-f', 'COST %M %U %S', *command], check=True,
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    line = [row for row in done.stderr.splitlines() if row.startswith('COST ')][-1]
    peak_kb, user, system = (float(v) for v in line.split()[1:])
    return user + system, peak_kb / 1024


def processes(path, options=()):
    """Return {'bare read': (CPU, RSS), 'replay': (CPU, RSS)} of whole processes on `path`."""
    import sys
    bare = process_cost([sys.executable, '-c', BARE_READ, str(path)])   # smaller: first
    ours = process_cost([sys.executable, '-m', 'quatcal_ros', 'replay', str(path),
                         '--link-topic', '/link_pose', '--sensor-topic', '/sensor_pose',
                         '--quiet', *options])
    return {'bare read': bare, 'replay': ours}


def best_seconds(function, repeats):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        times.append(time.perf_counter() - start)
    return min(times)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split('\n')[1])
    parser.add_argument('--minutes', type=float, default=10.0)
    parser.add_argument('--storage', nargs='+', choices=('sqlite3', 'mcap'),
                        default=['sqlite3', 'mcap'])
    parser.add_argument('--repeats', type=int, default=2)
    parser.add_argument('--profile', action='store_true')
    parser.add_argument('--processes', action='store_true')
    parser.add_argument('--estimate-time-offset', action='store_true')
    args = parser.parse_args()
    options = ('--estimate-time-offset',) if args.estimate_time_offset else ()
    start = time.perf_counter()
    messages, _ = recording(args.minutes)
    print(f'{len(messages)} messages ({args.minutes:g} min, link {LINK_RATE_HZ:g} Hz, sensor '
          f'{SENSOR_RATE_HZ:g} Hz) simulated in {time.perf_counter() - start:.1f} s\n')
    rows = []
    if args.processes:
        print('| storage | length | messages | bare read CPU s | replay CPU s | ratio | '
              'bare read peak MB | replay peak MB | ratio |')
        print('|---|---|---:|---:|---:|---:|---:|---:|---:|')
    with tempfile.TemporaryDirectory() as tmp:
        for storage in args.storage:
            path = f'{tmp}/{storage}'
            write_bag(path, TOPICS, messages, storage)
            if args.processes:
                cost = processes(path, options)
                (read_cpu, read_rss), (ours_cpu, ours_rss) = cost['bare read'], cost['replay']
                print(f'| {storage} | {args.minutes:g} min | {len(messages)} | {read_cpu:.1f} | '
                      f'{ours_cpu:.1f} | {ours_cpu / read_cpu:.2f} | {read_rss:.0f} | '
                      f'{ours_rss:.0f} | {ours_rss / read_rss:.2f} |')
                continue
            count = bare_read(path)
            read_s = best_seconds(lambda: bare_read(path), args.repeats)
            replay_s = best_seconds(lambda: replay(path), args.repeats)
            rows.append((storage, count, read_s, replay_s))
            if args.profile:
                profile = cProfile.Profile()
                profile.runcall(replay, path)
                print(f'--- replay profile ({storage}), top 25 by own time')
                pstats.Stats(profile).sort_stats('tottime').print_stats(25)
    if args.processes:
        return
    print('| storage | messages | bare read (msg/s) | replay (msg/s) | replay / read | '
          'target >= 0.5 |')
    print('|---|---:|---:|---:|---:|:---:|')
    for storage, count, read_s, replay_s in rows:
        ratio = read_s / replay_s
        print(f'| {storage} | {count} | {count / read_s:,.0f} | {count / replay_s:,.0f} | '
              f'{ratio:.2f} | {"yes" if ratio >= 0.5 else "no"} |')


if __name__ == '__main__':
    main()
