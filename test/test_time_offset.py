"""Time offset between the robot and sensor streams: synthetic known offsets and the ETH data."""

from dataclasses import replace

import numpy as np
import pytest
from quatcal_ros.core.calibration import CalibrationOptions
from quatcal_ros.report.page import offset_sentence
from quatcal_ros.sim import simulation
from quatcal_ros.stream.capture import CaptureConfig
from quatcal_ros.stream.session import SessionConfig
from quatcal_ros.stream.time_offset import estimate_time_offset
from quatcal_ros.stream.time_offset import find_time_offset
from quatcal_ros.stream.time_offset import refine_time_offset
from quatcal_ros.stream.time_offset import replay_streams
from quatcal_ros.stream.time_offset import WEAK_CORRELATION

MS = 1_000_000


@pytest.fixture(scope='module')
def streams():
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    return simulation.stop_and_go_streams(rng, cell, 12, rotation_noise_deg=0.3,
                                          translation_noise_m=0.001, latency_s=0.03)


def arrays(stream):
    return np.array([s for s, _ in stream]), np.array([p.quaternion for _, p in stream])


@pytest.mark.parametrize('late_ms', [0, 40, -70, 200])
def test_cross_correlation_finds_a_known_offset(streams, late_ms):
    link_stamps, link_q = arrays(streams.link)
    sensor_stamps, sensor_q = arrays(streams.sensor)
    found = estimate_time_offset(link_stamps, link_q, sensor_stamps + late_ms * MS, sensor_q)
    # A 200 Hz grid with parabolic peak interpolation, 30 Hz frames with 0.3 deg noise: the
    # peak lands within a fraction of a ms (measured 0.14-0.35 ms); 1.5 ms leaves room. (With
    # the speeds normalised over the whole grid instead of each overlap it was 0.6-4.3 ms.)
    assert abs(found.offset_ns + late_ms * MS) < 1.5 * MS
    assert 0.8 < found.correlation <= 1.0


@pytest.mark.parametrize('clock_ms', [0, 13, -120])
def test_exact_streams_give_their_offset_exactly(clock_ms):
    rng = np.random.default_rng(3)
    cell = simulation.random_cell(rng)
    streams = simulation.stop_and_go_streams(rng, cell, 10, latency_s=0.03,
                                             clock_offset_s=clock_ms / 1e3,
                                             drop_probability=0.0)
    found = estimate_time_offset(*arrays(streams.link), *arrays(streams.sensor))
    assert abs(found.offset_ns + clock_ms * MS) < 0.05 * MS
    itself = estimate_time_offset(*arrays(streams.link), *arrays(streams.link))
    assert itself.offset_ns == 0 and itself.correlation == pytest.approx(1.0)


def test_an_offset_beyond_the_search_is_refused_not_clamped(streams):
    link_stamps, link_q = arrays(streams.link)
    sensor_stamps, sensor_q = arrays(streams.sensor)
    # 700 ms late: the best lag within +-500 ms is the edge, which is no estimate
    with pytest.raises(ValueError, match='edge of the search.*beyond 500 ms'):
        estimate_time_offset(link_stamps, link_q, sensor_stamps + 700 * MS, sensor_q)
    found = estimate_time_offset(link_stamps, link_q, sensor_stamps + 450 * MS, sensor_q)
    assert abs(found.offset_ns + 450 * MS) < 5 * MS


def test_a_known_offset_centres_the_search(streams):
    """Two computers' clocks 2.3 s apart: searched around the offset given, not around 0."""
    link_stamps, link_q = arrays(streams.link)
    sensor_stamps, sensor_q = arrays(streams.sensor)
    late = sensor_stamps + 2300 * MS
    with pytest.raises(ValueError, match='beyond 500 ms are not searched'):
        estimate_time_offset(link_stamps, link_q, late, sensor_q)
    plain = estimate_time_offset(link_stamps, link_q, sensor_stamps, sensor_q)
    for centre_ms in (-2000, -2300, -2700):
        found = estimate_time_offset(link_stamps, link_q, late, sensor_q, centre_ns=centre_ms * MS)
        # the same alignment as on the stamps unshifted, to the grid's interpolation
        assert abs(found.offset_ns - (plain.offset_ns - 2300 * MS)) < 0.5 * MS, centre_ms
        assert found.correlation == pytest.approx(plain.correlation, abs=0.01)
    with pytest.raises(ValueError, match='offsets beyond 500 ms of -1.5 s are not searched'):
        estimate_time_offset(link_stamps, link_q, late, sensor_q, centre_ns=-1500 * MS)
    # find_time_offset centres on the session's own sensor offset, and says so.
    report, session = find_time_offset(
        [(int(s), p) for s, p in streams.link],
        [(int(s) + 2300 * MS, p) for s, p in streams.sensor],
        SessionConfig(sensor_offset_ns=-2200 * MS))
    assert abs(report.offset_ns + 2300 * MS) < 8 * MS
    assert report.to_json_dict()['searched_around_s'] == -2.2
    assert session.config.sensor_offset_ns == report.offset_ns
    assert 'searched_around_s' not in find_time_offset(
        streams.link, streams.sensor, SessionConfig())[0].to_json_dict()


def test_refinement_minimises_the_given_residual():
    assert abs(refine_time_offset(lambda t: (t - 12 * MS) ** 2, 0) - 12 * MS) < MS


def test_too_short_an_overlap_is_refused(streams):
    link_stamps, link_q = arrays(streams.link[:200])
    sensor_stamps, sensor_q = arrays(streams.sensor[:12])
    with pytest.raises(ValueError, match='overlap'):
        estimate_time_offset(link_stamps, link_q, sensor_stamps, sensor_q)


@pytest.mark.parametrize('sensor', ['two poses', 'one stamp', 'none'])
def test_a_stream_without_an_angular_speed_is_named(streams, sensor):
    """Two sensor poses, or a camera driver that froze its stamp, once raised an IndexError."""
    link_stamps, link_q = arrays(streams.link)
    sensor_stamps, sensor_q = arrays(streams.sensor)
    if sensor == 'two poses':
        sensor_stamps, sensor_q = sensor_stamps[:2], sensor_q[:2]
    elif sensor == 'one stamp':
        sensor_stamps = np.full_like(sensor_stamps, sensor_stamps[5])
    else:
        sensor_stamps, sensor_q = sensor_stamps[:0], sensor_q[:0]
    with pytest.raises(ValueError, match='the sensor stream has .* distinct stamps'):
        estimate_time_offset(link_stamps, link_q, sensor_stamps, sensor_q)


def test_eth_recording_offset_and_residuals(eth_streams):
    config = SessionConfig(capture=CaptureConfig(mode='continuous', continuous_step_deg=10.0),
                           calibration=CalibrationOptions(invert_sensor=True))
    report, session = find_time_offset(*eth_streams, config)
    # Measured here: the camera stamps are about 24 ms late (offset -24.4 ms), and applying
    # the offset lowers the RMS residual from 0.81 to 0.72 deg.
    assert -40 * MS < report.offset_ns < -5 * MS
    assert report.residual_with_deg < report.residual_without_deg
    session.estimate()
    assert session.result is not None and session.result.residual_rms_deg < 1.0


def test_speeds_that_align_nowhere_in_the_search_are_not_taken_for_an_offset(eth_streams):
    # The ETH camera's clock 3 s ahead, searched within 0.5 s of 0: the correlation peaked at
    # -0.08 (at -333 ms) and that lag was applied as if found.
    link, camera = eth_streams
    ahead = [(stamp + 3_000 * MS, pose) for stamp, pose in camera]
    config = SessionConfig(capture=CaptureConfig(mode='continuous'),
                           calibration=CalibrationOptions(invert_sensor=True))
    report, _ = find_time_offset(link, ahead, config)
    assert report.correlation < WEAK_CORRELATION and report.unaligned_ns is not None
    assert abs(report.offset_ns) <= 50 * MS   # the residual's own search, around 0
    found = report.to_json_dict()
    assert found['speeds_aligned'] is False and found['searched_within_s'] == 0.5
    assert 'align nowhere within 500 ms of +0.000 s (best correlation -0.08, at ' \
        in offset_sentence(found)
    # Given near the truth, the same speeds align, and the words stay as they were.
    near = find_time_offset(link, ahead, replace(config, sensor_offset_ns=-2_900 * MS))[0]
    assert near.correlation > 0.5 and abs(near.offset_ns + 3_020 * MS) < 15 * MS
    assert near.to_json_dict()['speeds_aligned']
    assert 'align nowhere' not in offset_sentence(near.to_json_dict())
    # Its residuals are the search's, not the capture's residual_rms_deg (they moved apart).
    assert ('RMS residual of the search (the same sensor frames, the link at each shifted '
            "stamp: not the capture's residual_rms_deg)") in offset_sentence(found)


def test_the_simulated_clock_offset_mode_is_found_and_undone():
    """A sensor clock 80 ms ahead: stamps move, nothing else; the offset found and undone."""
    def make(offset_s):
        rng = np.random.default_rng(3)
        cell = simulation.random_cell(rng)
        return simulation.stop_and_go_streams(rng, cell, 12, rotation_noise_deg=0.3,
                                              translation_noise_m=0.001, latency_s=0.03,
                                              clock_offset_s=offset_s)
    plain, ahead = make(0.0), make(0.08)
    assert [s + 80 * MS for s, _ in plain.sensor] == [s for s, _ in ahead.sensor]
    assert all(np.array_equal(a.quaternion, b.quaternion)
               for (_, a), (_, b) in zip(plain.sensor, ahead.sensor))
    assert plain.sensor_delivery_ns == ahead.sensor_delivery_ns
    assert [s for s, _ in plain.link] == [s for s, _ in ahead.link]
    config = SessionConfig()
    report, _ = find_time_offset(ahead.link, ahead.sensor, config)
    # Still samples do not see the offset (the residual is flat): the cross-correlation's
    # estimate stands, within its tolerance above.
    assert abs(report.offset_ns + 80 * MS) < 8 * MS
    undone = replay_streams(ahead.link, ahead.sensor, config, -80 * MS).samples
    samples = replay_streams(plain.link, plain.sensor, config).samples
    assert len(samples) >= 10 and len(undone) == len(samples)
    for a, b in zip(undone, samples):
        assert a.stamp_ns == b.stamp_ns
        np.testing.assert_allclose(a.link.as_matrix(), b.link.as_matrix(), atol=1e-12)
        np.testing.assert_allclose(a.sensor.as_matrix(), b.sensor.as_matrix(), atol=1e-12)


def test_each_offset_is_scored_once(streams, monkeypatch):
    """Every residual the search and its report ask for is one calibration, however often."""
    from quatcal_ros.stream import time_offset
    scored, calibrate = [], time_offset.calibrate

    def counting(samples, options):
        scored.append(samples[0].stamp_ns)   # a frame's stamp plus the offset scored
        return calibrate(samples, options)
    monkeypatch.setattr(time_offset, 'calibrate', counting)
    report, _ = find_time_offset(streams.link, streams.sensor, SessionConfig())
    assert len(scored) >= 10   # the golden-section search, then the residuals reported
    assert len(set(scored)) == len(scored)


def test_a_recording_of_two_runs_is_searched_on_one_and_replayed_whole():
    """
    Stamps that start over (a clock restart, a looped bag): each run is one timeline.

    The search once interpolated across the restart: -75.7 ms for a -30 ms offset, and half
    the samples lost.
    """
    rng = np.random.default_rng(11)
    cell = simulation.random_cell(rng)
    runs = [simulation.stop_and_go_streams(rng, cell, 8, rotation_noise_deg=0.3,
                                           translation_noise_m=0.001, latency_s=0.03,
                                           clock_offset_s=0.03) for _ in range(2)]
    start = runs[1].link[0][0]
    back = start - runs[0].link[0][0] + 7 * MS   # the second run restarts the clock

    def shifted(stream):
        return [(stamp - back, pose) for stamp, pose in stream]
    link = runs[0].link + shifted(runs[1].link)
    sensor = runs[0].sensor + shifted(runs[1].sensor)
    config = SessionConfig()
    report, session = find_time_offset(link, sensor, config)
    assert report.runs == 2 and report.to_json_dict()['runs'] == 2
    busiest = max(range(2), key=lambda k: len(runs[k].sensor))
    alone, _ = find_time_offset(runs[busiest].link, runs[busiest].sensor, config)
    assert report.offset_ns == alone.offset_ns   # that run's search, not across the restart
    assert abs(report.offset_ns + 30 * MS) < 10 * MS   # still stops: the correlation's bound
    each = [len(replay_streams(run.link, run.sensor, config, report.offset_ns).samples)
            for run in runs]
    assert len(session.samples) == sum(each) and session.counters['time_jumps'] == 1
    with pytest.raises(ValueError, match='the link stamps start over 1 time.s. and the sensor '
                                         'stamps 0 time.s.: the runs cannot be matched'):
        find_time_offset(link, runs[0].sensor, config)


def test_the_replays_recorder_gives_the_search_its_streams(streams):
    """The replay's recorder keeps the streams as rows (_StreamRecorder): the same search."""
    from quatcal_ros.tools.cli import _StreamRecorder
    recorder = _StreamRecorder()
    for stream, messages in (('link', streams.link), ('sensor', streams.sensor)):
        half = len(messages) // 2   # as the bag gives them: runs of rows, and single poses
        recorder.add_poses(stream, [s for s, _ in messages[:half]],
                           np.array([p.position for _, p in messages[:half]]),
                           np.array([p.quaternion for _, p in messages[:half]]))
        add = recorder.add_link_pose if stream == 'link' else recorder.add_sensor_pose
        for stamp, pose in messages[half:]:
            add(stamp, pose)
    config = SessionConfig()
    listed, from_list = find_time_offset(streams.link, streams.sensor, config)
    recorded, from_recorder = find_time_offset(recorder.link, recorder.sensor, config)
    assert recorded == listed and len(from_list.samples) >= 10
    assert [s.stamp_ns for s in from_recorder.samples] == \
        [s.stamp_ns for s in from_list.samples]


def test_streams_out_of_order_are_refused_by_the_replay(streams):
    """The link poses between two sensor poses are found by their stamps: sorted ones only."""
    looped = streams.link + streams.link
    with pytest.raises(ValueError, match='the link stamps are not in order'):
        replay_streams(looped, streams.sensor, SessionConfig())


def test_the_search_skips_a_run_without_a_link_speed():
    """The run with the most sensor poses had two link poses: the search failed on it."""
    rng = np.random.default_rng(12)
    cell = simulation.random_cell(rng)
    run = simulation.stop_and_go_streams(rng, cell, 8, rotation_noise_deg=0.3,
                                         translation_noise_m=0.001, latency_s=0.03)
    start = run.link[0][0]
    back = 10**12   # a second run a thousand seconds earlier: a few link poses, many frames
    link = run.link + [(start - back, run.link[0][1]), (start - back + MS, run.link[1][1])]
    sensor = run.sensor + [(stamp - back, pose) for stamp, pose in run.sensor + run.sensor[:5]]
    sensor = sensor[:len(run.sensor)] + sorted(sensor[len(run.sensor):], key=lambda m: m[0])
    report, _ = find_time_offset(link, sensor, SessionConfig())
    alone, _ = find_time_offset(run.link, run.sensor, SessionConfig())
    assert report.runs == 2 and report.offset_ns == alone.offset_ns


def test_angular_speed_in_chunks_equals_at_once(streams, monkeypatch):
    from quatcal_ros.stream import time_offset
    stamps, quaternions = arrays(streams.link)
    whole = time_offset.angular_speed(stamps, quaternions)
    monkeypatch.setattr(time_offset, 'SPEED_CHUNK', 7)
    chunked = time_offset.angular_speed(stamps, quaternions)
    assert len(whole[1]) > 7 * 10
    np.testing.assert_array_equal(chunked[0], whole[0])
    # the same arithmetic; numpy's vector loops may round a chunk's tail differently
    np.testing.assert_allclose(chunked[1], whole[1], rtol=1e-12, atol=1e-15)
