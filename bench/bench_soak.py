#!/usr/bin/env python3
"""
The calibrator process under real-time load: rates, lateness, backlog and memory over a soak.

The timing half of test/test_soak.py (which paces the same streams by the node's counts and
asserts only counts and memory).  Here this script publishes simulated stop-and-go streams in
real time, stamped on the wall clock like a live robot and camera (in batches per tick of a
few milliseconds), to `python -m quatcal_ros calibrator`, and reads /diagnostics and
/proc/PID/status (VmRSS once a second, VmHWM for the peak):
- soak: link poses at 1 kHz and sensor poses at 60 Hz for --soak-s seconds (default 60);
- flood: 2 kHz of NaN poses on sensor_pose from another node, among good streams at 200 Hz
  and 30 Hz, for --flood-s seconds (default 16).
Targets (what the soak test asserted before it lost its timing): the link stream published at
over 999 Hz with a median lateness under 20 ms; RSS growth from the 2nd to the last quarter
under 6 MB; no growing backlog (the last quarter's median lag at most 50 over the 2nd's, its
maximum under the node's link queue of 1000); every link pose and 99 % of the sensor poses
received; under the flood, 95 % of the bad poses counted and 97 % of the good sensor poses.

Run: python bench/bench_soak.py [--soak-s 60] [--flood-s 16]
(A domain id reserved on this host by test/ros_domains.py unless ROS_DOMAIN_ID is set;
discovery on this machine only.)
"""

import argparse
import os
from pathlib import Path
import shutil
import sys
import tempfile
import time

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO_ROOT / 'test'))      # the test's harness and domain allocator
NS = 1_000_000_000
TICK_S = 0.004
PARAMETERS = ('diagnostics_period_s:=0.5', 'still_window_s:=0.3')
LINK_DEPTH = 1000   # the node's link_pose subscription queue (qos.LINK_QOS)


def run_real_time(driver, streams, process, flood_hz=0.0, on_second=None):
    """
    Publish `streams` in real time (stamps are wall-clock ns); return per-tick lateness (ns).

    flood_hz: NaN poses per second on sensor_pose from another node (stamped now).
    on_second(): called about once per second (memory sampling).
    """
    link = streams.link
    sensor = list(zip(streams.sensor_delivery_ns, streams.sensor))
    lateness = []
    i = j = 0
    flood_due = time.time_ns()
    next_second = time.monotonic() + 1.0
    while i < len(link) or j < len(sensor):
        now = time.time_ns()
        if i < len(link) and link[i][0] <= now:
            lateness.append(now - link[i][0])
        while i < len(link) and link[i][0] <= now:
            driver.publish('link', *link[i])
            i += 1
        while j < len(sensor) and sensor[j][0] <= now:
            driver.publish('sensor', *sensor[j][1])
            j += 1
        while flood_hz and flood_due <= now:
            driver.publish('flood', flood_due)
            flood_due += int(NS / flood_hz)
        if time.monotonic() >= next_second:
            next_second += 1.0
            if process.poll() is not None:
                raise SystemExit(f'the calibrator exited: {process.returncode}')
            if on_second:
                on_second()
        driver.spin_some()
        time.sleep(max(0.0, TICK_S - (time.time_ns() - now) / NS))
    return lateness


def drain(driver, process, published):
    """Wait until the node has counted every link pose and reported once more."""
    end = time.monotonic()
    driver.wait_for(lambda: (driver.received()[0] >= published['link']
                             and driver.statuses[-1][0] > end + 0.6),
                    30.0, 'the calibrator to catch up', process)
    return end


def soak(workdir, domain_id, seconds):
    """Return the soak's figures (a dict)."""
    from ros_harness import stop_process
    from soak_harness import Driver, error_deg, make_streams, proc_status_kb, start_calibrator

    process = start_calibrator(workdir, domain_id, *PARAMETERS)
    driver = Driver(domain_id)
    memory = []     # (monotonic time, VmRSS kB)
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(11, seconds, 1000.0, 60.0, time.time_ns() + 2 * NS)
        start = time.monotonic()
        lateness = run_real_time(
            driver, streams, process,
            on_second=lambda: memory.append((time.monotonic(),
                                             proc_status_kb(process.pid, 'VmRSS'))))
        published = dict(driver.published)
        end = drain(driver, process, published)
        peak_kb = proc_status_kb(process.pid, 'VmHWM')
        values = driver.latest()
    finally:
        stop_process(process, timeout=20.0)
        driver.close()
    quarter = (end - start) / 4

    def quarters(times):
        """Masks of the 2nd and the last quarter of the run, for times since its start."""
        return {'2nd': (times >= quarter) & (times < 2 * quarter), 'last': times >= 3 * quarter}
    rss = np.array([kb for _, kb in memory])
    rss_in = quarters(np.array([t - start for t, _ in memory]))
    lags = np.array([(t - start, sent - int(v['link_messages']))
                     for t, sent, v in driver.statuses if start <= t <= end])
    lag = {name: lags[mask, 1] for name, mask in quarters(lags[:, 0]).items()}
    stream_s = (streams.link[-1][0] - streams.link[0][0]) / NS
    return {
        'stream_s': stream_s, 'published': published,
        'link_hz': (published['link'] - 1) / stream_s,
        'late_ms': np.percentile(lateness, [50, 99]) / 1e6,
        'received': (int(values['link_messages']), int(values['sensor_messages'])),
        'bad': int(values['bad_messages']),
        'rss_mb': {name: rss[mask].mean() / 1024 for name, mask in rss_in.items()},
        'peak_mb': peak_kb / 1024,
        'lag': {name: (float(np.median(v)), int(v.max())) for name, v in lag.items()},
        'samples': int(values['samples']), 'stops': len(streams.stops),
        'uncertainty_deg': float(values['uncertainty_deg']),
        'error_deg': error_deg(driver.rotations[-1], streams.truth)}


def flood(workdir, domain_id, seconds):
    """Return the flood's figures (a dict)."""
    from ros_harness import stop_process
    from soak_harness import Driver, error_deg, make_streams, start_calibrator

    process = start_calibrator(workdir, domain_id, *PARAMETERS)
    driver = Driver(domain_id)
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(12, seconds, 200.0, 30.0, time.time_ns() + 2 * NS,
                               still_s=0.5, move_s=0.5)
        start = time.monotonic()
        run_real_time(driver, streams, process, flood_hz=2000.0)
        wall = time.monotonic() - start
        published = dict(driver.published)
        drain(driver, process, published)
        values = driver.latest()
    finally:
        stop_process(process, timeout=20.0)
        driver.close()
    bad = int(values.get('bad_sensor_pose_non_finite', 0))
    return {'wall_s': wall, 'published': published, 'bad': bad,
            'good_sensor': int(values['sensor_messages']) - bad,
            'link': int(values['link_messages']), 'samples': int(values['samples']),
            'stops': len(streams.stops), 'uncertainty_deg': float(values['uncertainty_deg']),
            'error_deg': error_deg(driver.rotations[-1], streams.truth)}


def met(ok):
    return 'met' if ok else 'NOT met'


def print_soak(s):
    sent, (link, sensor) = s['published'], s['received']
    print(f'Soak: {s["stream_s"]:.0f} s, link 1 kHz and sensor 60 Hz in real time; '
          f'{s["samples"]} samples of {s["stops"]} stops, uncertainty '
          f'{s["uncertainty_deg"]:.4f} deg, true error {s["error_deg"]:.4f} deg\n')
    print('| figure | value | target |')
    print('|---|---|---|')
    rows = [
        ('link rate published (Hz)', f'{s["link_hz"]:.1f}', '> 999', s['link_hz'] > 999.0),
        ('lateness of a tick, median / 99th pct (ms)',
         f'{s["late_ms"][0]:.1f} / {s["late_ms"][1]:.1f}', 'median < 20', s['late_ms'][0] < 20),
        ('link poses received / published', f'{link} / {sent["link"]}', 'all',
         link == sent['link']),
        ('sensor poses received / published', f'{sensor} / {sent["sensor"]}', '>= 99 %',
         sensor >= 0.99 * sent['sensor']),
        ('bad messages', f'{s["bad"]}', '0', s['bad'] == 0),
        ('RSS 2nd / last quarter (MB)',
         f'{s["rss_mb"]["2nd"]:.1f} / {s["rss_mb"]["last"]:.1f}', 'growth < 6 MB',
         s['rss_mb']['last'] - s['rss_mb']['2nd'] < 6.0),
        ('peak RSS, VmHWM (MB)', f'{s["peak_mb"]:.1f}', '', None),
        ('link lag (published - received), 2nd quarter: median / max',
         '%.0f / %d' % s['lag']['2nd'], '', None),
        ('link lag, last quarter: median / max', '%.0f / %d' % s['lag']['last'],
         f'median <= 2nd + 50, max < {LINK_DEPTH}',
         s['lag']['last'][0] <= s['lag']['2nd'][0] + 50 and s['lag']['last'][1] < LINK_DEPTH),
    ]
    for label, value, target, ok in rows:
        print(f'| {label} | {value} | {target + ": " + met(ok) if target else ""} |')


def print_flood(f):
    sent = f['published']
    print(f'\nFlood: {f["wall_s"]:.0f} s, 2 kHz of NaN poses on sensor_pose beside link 200 Hz '
          f'and sensor 30 Hz; {f["samples"]} samples of {f["stops"]} stops, uncertainty '
          f'{f["uncertainty_deg"]:.4f} deg, true error {f["error_deg"]:.4f} deg\n')
    print('| figure | counted / published | target |')
    print('|---|---|---|')
    for label, count, total, share in (('bad (NaN) poses', f['bad'], sent['flood'], 0.95),
                                       ('good sensor poses', f['good_sensor'], sent['sensor'],
                                        0.97),
                                       ('link poses', f['link'], sent['link'], 1.0)):
        print(f'| {label} | {count} / {total} | >= {share:.0%}: {met(count >= share * total)} |')


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    parser.add_argument('--soak-s', type=float, default=60.0,
                        help='length of the soak (default 60 s)')
    parser.add_argument('--flood-s', type=float, default=16.0,
                        help='length of the flood (default 16 s)')
    args = parser.parse_args(argv)
    import ros_domains
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    reservation = None
    if 'ROS_DOMAIN_ID' in os.environ:
        domain_id = int(os.environ['ROS_DOMAIN_ID'])
    else:
        reservation = ros_domains.reserve()
        domain_id = reservation.domain_id
    workdir = Path(tempfile.mkdtemp(prefix='bench_soak_'))
    try:
        (workdir / 'soak').mkdir()
        (workdir / 'flood').mkdir()
        print_soak(soak(workdir / 'soak', domain_id, args.soak_s))
        print_flood(flood(workdir / 'flood', domain_id, args.flood_s))
    finally:
        if reservation is not None:
            reservation.release()
    shutil.rmtree(workdir, ignore_errors=True)
    return 0


if __name__ == '__main__':
    sys.exit(main())
