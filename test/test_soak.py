"""
Load tests through the real middleware: a soak of a 1 kHz + 60 Hz stream, and a bad-message flood.

Counts and memory only: nothing here depends on how fast the machine is.

The calibrator runs as a process (`python -m quatcal_ros calibrator`), so that its memory can
be read from /proc/PID/status (VmRSS sampled as the stream goes, VmHWM for the peak).  The
test process publishes simulated stop-and-go streams (simulation.stop_and_go_streams), in
delivery order, paced by the node's own counts on /diagnostics: at most a window of messages
is in flight at any time (well within every queue on the way, including the best-effort
sensor_pose subscription), so a loaded machine only makes the run longer, and every message
must be accounted for.  The stamps are the simulation's, so the node's check of stamps
against its clock is off.  How fast the node keeps up with the same streams in real time
(rates, lateness, backlog, latency) is measured by bench/bench_soak.py, not asserted here.

- Soak (QUATCAL_SOAK_S seconds of stream, default 20): link poses at 1 kHz and sensor poses
  at 60 Hz (stamp spacing).  Every message is counted, none is bad; the RSS of the last
  quarter of the stream is within a few MB of the second quarter's; the estimate converges to
  the truth within 3x its uncertainty.  The peak RSS is printed (pytest -s) and part of the
  assertion messages.
- Flood: NaN poses on sensor_pose from another publisher, 2000 per second of stream, among
  the good streams (200 Hz and 30 Hz): every bad message is counted as bad, every good one as
  good, the stops are still sampled and the estimate converges; the warning about the bad
  ones is throttled to one per 5 s.

On domain ids reserved on this host (conftest's domain_id).
"""

import os
import time

import numpy as np
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.sim import simulation
from ros_harness import stop_process
from soak_harness import Driver
from soak_harness import error_deg
from soak_harness import make_streams
from soak_harness import proc_status_kb
from soak_harness import start_calibrator

NS = NS_PER_S
SOAK_S = float(os.environ.get('QUATCAL_SOAK_S', '20'))
# Messages published but not yet counted by the node, at most, per topic.  Both together stay
# below Fast DDS's shared-memory port queue (512) and far below every history depth (1000).
LINK_WINDOW = 300
SENSOR_WINDOW = 200
# The RSS of the last quarter of the soak may exceed the second quarter's by this much.
RSS_GROWTH_LIMIT_KB = 6 * 1024
PARAMETERS = ('diagnostics_period_s:=0.1', 'still_window_s:=0.3', 'max_stamp_offset_s:=0.0')
# A safety net for a hung node only: the runs take a fraction of this even on a loaded machine.
WALL_LIMIT_S = 600.0


def feed(driver, streams, process, flood_per_s=0.0, every_links=None, on_links=None):
    """
    Publish the streams in delivery order, paced by the node's counts; return when all are in.

    flood_per_s: NaN poses on sensor_pose per second of stream, stamped on the stream's clock.
    on_links(): called after every `every_links` link poses (memory sampling).
    """
    events = streams.delivery_order()
    flood_period_ns = int(NS / flood_per_s) if flood_per_s else None
    flood_due = events[0][0]
    deadline = time.monotonic() + WALL_LIMIT_S

    def in_flight():
        link, sensor = driver.received()
        return (driver.published['link'] - link,
                driver.published['sensor'] + driver.published['flood'] - sensor)

    def wait_for_room(link_room, sensor_room):
        while True:
            link, sensor = in_flight()
            if link + link_room <= LINK_WINDOW and sensor + sensor_room <= SENSOR_WINDOW:
                return
            assert process.poll() is None, f'the calibrator exited: {process.returncode}'
            assert time.monotonic() < deadline, f'the node stopped counting: {in_flight()}'
            driver.spin_some(0.02)

    for k, (due, kind, stamp, pose) in enumerate(events):
        while flood_period_ns and flood_due <= due:
            wait_for_room(0, 1)
            driver.publish('flood', flood_due)
            flood_due += flood_period_ns
        wait_for_room(kind == 'link', kind == 'sensor')
        driver.publish(kind, stamp, pose)
        if kind == 'link' and on_links and driver.published['link'] % every_links == 0:
            on_links()
        if k % 50 == 0:
            driver.spin_some()
    total = dict(driver.published)
    driver.wait_for(lambda: driver.received() == (total['link'],
                                                  total['sensor'] + total['flood']),
                    120.0, f'the node to count every message of {total}', process)


def test_soak_1khz_link_60hz_sensor(tmp_path, domain_id):
    process = start_calibrator(tmp_path, domain_id, *PARAMETERS)
    driver = Driver(domain_id)
    memory = []     # (link poses published, VmRSS kB)
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(11, max(SOAK_S, 4.0), 1000.0, 60.0, simulation.DEFAULT_START_NS)
        feed(driver, streams, process, every_links=500,
             on_links=lambda: memory.append((driver.published['link'],
                                             proc_status_kb(process.pid, 'VmRSS'))))
        published = dict(driver.published)
        driver.wait_for(lambda: driver.rotations and int(driver.latest()['samples']) > 0,
                        60.0, 'an estimate', process)
        peak_kb = proc_status_kb(process.pid, 'VmHWM')
        values = driver.latest()
    finally:
        status = stop_process(process, timeout=30.0)
        driver.close()
    log = (tmp_path / 'calibrator.log').read_text()
    assert status == 0, log[-3000:]

    links = np.array([n for n, _ in memory])
    rss = np.array([kb for _, kb in memory])
    quarter = published['link'] / 4
    second = rss[(links >= quarter) & (links < 2 * quarter)]
    last = rss[links >= 3 * quarter]
    growth_kb = float(last.mean() - second.mean())
    uncertainty = float(values['uncertainty_deg'])
    error = error_deg(driver.rotations[-1], streams.truth)
    report = (f'soak of {SOAK_S:g} s of stream: published {published["link"]} link and '
              f'{published["sensor"]} sensor poses; the node counted {values["link_messages"]}'
              f' and {values["sensor_messages"]}, {values["bad_messages"]} bad; peak RSS '
              f'(VmHWM) {peak_kb / 1024:.1f} MB; RSS 2nd quarter {second.mean() / 1024:.1f} '
              f'MB, last quarter {last.mean() / 1024:.1f} MB (growth {growth_kb / 1024:+.2f} '
              f'MB); {values["samples"]} samples of {len(streams.stops)} stops, uncertainty '
              f'{uncertainty:.4f} deg, true error {error:.4f} deg')
    print('\n' + report)
    assert len(second) >= 2 and len(last) >= 2, report
    assert growth_kb < RSS_GROWTH_LIMIT_KB, report
    # Nothing lost, nothing misread: every pose counted once, and as good.
    assert int(values['link_messages']) == published['link'], report
    assert int(values['sensor_messages']) == published['sensor'], report
    assert values['bad_messages'] == '0', report
    assert int(values['samples']) >= 0.8 * len(streams.stops), report
    assert error < 3.0 * uncertainty, report


def test_flood_of_bad_messages_does_not_starve_good_ones(tmp_path, domain_id):
    process = start_calibrator(tmp_path, domain_id, *PARAMETERS)
    driver = Driver(domain_id)
    try:
        driver.wait_for_calibrator(process)
        streams = make_streams(12, 8.0, 200.0, 30.0, simulation.DEFAULT_START_NS,
                               still_s=0.5, move_s=0.5)
        start = time.monotonic()
        feed(driver, streams, process, flood_per_s=2000.0)
        flood_wall_s = time.monotonic() - start
        published = dict(driver.published)
        driver.wait_for(lambda: driver.rotations, 60.0, 'an estimate', process)
        values = driver.latest()
    finally:
        status = stop_process(process, timeout=30.0)
        driver.close()
    log = (tmp_path / 'calibrator.log').read_text()
    assert status == 0, log[-3000:]
    bad = int(values.get('bad_sensor_pose_non_finite', 0))
    good_sensor = int(values['sensor_messages']) - bad
    uncertainty = float(values['uncertainty_deg'])
    error = error_deg(driver.rotations[-1], streams.truth)
    report = (f'flood: published {published["flood"]} NaN, {published["sensor"]} good sensor '
              f'and {published["link"]} link poses; node counted {bad} bad, {good_sensor} good '
              f'sensor, {values["link_messages"]} link poses; {values["samples"]} samples of '
              f'{len(streams.stops)} stops, uncertainty {uncertainty:.4f} deg, true error '
              f'{error:.4f} deg')
    print('\n' + report)
    assert published['flood'] >= 2000 * 7, report
    assert bad == published['flood'], report                        # each one counted as bad
    assert int(values['bad_messages']) == bad, report               # and for that reason only
    assert good_sensor == published['sensor'], report               # none starved
    assert int(values['link_messages']) == published['link'], report
    assert int(values['samples']) >= len(streams.stops) - 2, report
    assert error < 3.0 * uncertainty, report
    # One warning per reason and 5 s (steady clock), naming the topic: however long the flood
    # took, the first one and at most one per 5 s after it.
    warnings = log.count('/sensor_pose: bad message skipped (non_finite')
    assert 1 <= warnings <= 1 + int(flood_wall_s // 5), log[-3000:]
