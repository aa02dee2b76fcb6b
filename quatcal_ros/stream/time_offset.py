"""
Time offset between the link and sensor streams, estimated from the data.

The rotation angle of a motion is the same for the link and the sensor (A_a and A_b are
similar matrices, Lemma 4 of Shiu and Ahmad), in any frame convention. So the angular speed
of the two streams is one signal seen twice, and the lag that best aligns the two speed curves
is the offset between their clocks. This is the approach of ETH's hand_eye_calibration (Furrer
et al. 2017). `estimate_time_offset` finds that lag by cross-correlation on a common time grid.
`refine_time_offset` then minimises any residual function of the offset (the caller runs its
calibration) by a golden-section search around it.

Sign: the returned offset is added to the sensor stamps. A camera that stamps frames 30 ms too
late needs an offset of -30 ms.
"""

from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import calibrate
from quatcal_ros.core.numerics import finite_or_none
from quatcal_ros.core.pose import Sample
from quatcal_ros.core.solver import DegenerateMotionError
from quatcal_ros.core.units import NS_PER_S
from quatcal_ros.stream.pairing import LINK
from quatcal_ros.stream.recorded_stream import RecordedStream
from quatcal_ros.stream.session import Session


# A relative change of the RMS residual below this is no evidence about the offset.
FLAT_RESIDUAL = 1e-6
# Poses whose angular speeds are computed at once.
SPEED_CHUNK = 1 << 16
# A best correlation below this aligns nothing: speed curves that share no motion at any lag
# searched score about 0 (the ETH arm recording's 3 s offset searched within 0.5 s: -0.08, at
# -333 ms); aligned, 0.67 on that recording and above 0.8 on the simulated streams.
WEAK_CORRELATION = 0.3


@dataclass(frozen=True)
class TimeOffset:
    """An estimated offset (add to sensor stamps) and how clear the alignment was."""

    offset_ns: int
    correlation: float      # normalised cross-correlation at the offset, in [-1, 1]


def link_speed_deg_s(samples):
    """
    Return the median speed (deg/s) the link turned at between consecutive samples, or None.

    Samples taken while the robot moves (continuous capture) shift by this much per second
    of an offset between the two streams' stamps.
    """
    stamps = np.array([s.stamp_ns for s in samples], dtype=np.int64)
    if len(stamps) < 2:
        return None
    q = np.array([s.link.quaternion for s in samples])
    dt = np.diff(stamps) / NS_PER_S
    keep = dt > 0
    if not keep.any():
        return None
    return float(np.degrees(np.median(quat.angle_between(q[:-1], q[1:])[keep] / dt[keep])))


def angular_speed(stamps_ns, quaternions, baseline_s=0.1):
    """
    Return (times in s, angular speed in rad/s) of a pose stream.

    Each speed spans about `baseline_s`, which averages out single-frame orientation noise.
    The times are relative to the first stamp of the stream (float seconds, exact enough for
    differences).
    """
    stamps_ns = np.asarray(stamps_ns, dtype=np.int64)
    t = (stamps_ns - stamps_ns[0]) / NS_PER_S
    q = np.asarray(quaternions, dtype=float)
    if len(t) < 3:
        return t[:0], t[:0]
    period = np.median(np.diff(t))
    step = max(1, int(round(baseline_s / max(period, 1e-6))))
    step = min(step, len(t) - 1)
    dt = t[step:] - t[:-step]
    # in chunks: the quaternion products' temporaries of a long stream took some 100 MB
    pairs = len(t) - step   # (k, k + step)
    angle = np.concatenate([
        quat.angle_between(q[first:last], q[first + step:last + step])
        for first, last in ((k, min(k + SPEED_CHUNK, pairs))
                            for k in range(0, pairs, SPEED_CHUNK))])
    keep = dt > 0
    return ((t[step:] + t[:-step])[keep] / 2.0), angle[keep] / dt[keep]


def estimate_time_offset(link_stamps_ns, link_quaternions, sensor_stamps_ns,
                         sensor_quaternions, max_offset_s=0.5, grid_hz=200.0, centre_ns=0):
    """
    Cross-correlate the angular speeds of both streams; return a TimeOffset.

    The offsets searched lie within max_offset_s of centre_ns (a known offset, such as the
    clock difference of two unsynchronised computers). Not wider by default: a robot that
    stops at a steady rhythm has speed curves that align about as well one period away.
    ValueError when a stream gives no speed curve (fewer than 3 poses, or all at one stamp)
    or the streams overlap too briefly, saying which.
    """
    sensor_stamps_ns = np.asarray(sensor_stamps_ns, dtype=np.int64) + int(centre_ns)
    streams = (('link', link_stamps_ns, link_quaternions),
               ('sensor', sensor_stamps_ns, sensor_quaternions))
    for name, stamps, _ in streams:
        distinct = len(np.unique(np.asarray(stamps, dtype=np.int64)))
        if distinct < 3:
            raise ValueError(f'the {name} stream has {len(stamps)} poses at {distinct} '
                             'distinct stamps: its angular speed needs poses at 3 or more')
    (t_l, w_l), (t_s, w_s) = (angular_speed(stamps, q) for _, stamps, q in streams)
    if not len(t_l) or not len(t_s):   # stamps out of order across the whole stream
        raise ValueError("a stream's stamps go back in time: no angular speed")
    origin = int(min(link_stamps_ns[0], sensor_stamps_ns[0]))
    t_l = t_l + (int(link_stamps_ns[0]) - origin) / NS_PER_S
    t_s = t_s + (int(sensor_stamps_ns[0]) - origin) / NS_PER_S
    start, end = max(t_l[0], t_s[0]), min(t_l[-1], t_s[-1])
    if end - start < 4 * max_offset_s:
        raise ValueError(f'the streams overlap for only {end - start:.1f} s: at least '
                         f'{4 * max_offset_s:.1f} s of common motion are needed')
    grid = np.arange(start, end, 1.0 / grid_hz)
    link = np.interp(grid, t_l, w_l)
    sensor = np.interp(grid, t_s, w_s)
    max_lag = int(round(max_offset_s * grid_hz))
    lags = np.arange(-max_lag, max_lag + 1)
    # correlation[k]: sensor shifted by lags[k] samples against the link.
    correlation = np.array([_overlap_correlation(link, sensor, lag) for lag in lags])
    best = int(np.argmax(correlation))
    shift = float(lags[best])
    if best in (0, len(lags) - 1):   # the peak may lie beyond: not an estimate
        edge_ms = (centre_ns / NS_PER_S - shift / grid_hz) * 1e3
        around = f' of {centre_ns / NS_PER_S:+g} s' if centre_ns else ''
        raise ValueError(f'the angular speeds align best at the edge of the search, a sensor '
                         f'offset of {edge_ms:+.0f} ms: offsets beyond {max_offset_s * 1e3:g} '
                         f'ms{around} are not searched; give the offset you expect with '
                         '--sensor-time-offset, and the search looks around it')
    a, b, c = correlation[best - 1:best + 2]   # parabola through the peak and its neighbours
    denominator = a - 2.0 * b + c
    if denominator < 0.0:
        shift += 0.5 * (a - c) / denominator
    return TimeOffset(int(centre_ns) + int(round(-shift / grid_hz * NS_PER_S)),
                      float(correlation[best]))


def _overlap_correlation(link, sensor, lag):
    """
    Return the correlation coefficient of link(t) and sensor(t + lag) over their overlap.

    Centred and scaled over the overlap itself: with both signals normalised once over the
    whole grid, the still stretches at the ends (below the mean speed) dropped out of the
    overlap as the lag grew, which favoured lags next to the true one (3.5 ms off on exact
    data, and a correlation above 1).
    """
    if lag >= 0:
        a, b = link[:len(link) - lag], sensor[lag:]
    else:
        a, b = link[-lag:], sensor[:len(sensor) + lag]
    if len(a) < 2:
        return -np.inf
    a, b = a - a.mean(), b - b.mean()
    norm = float(np.sqrt((a @ a) * (b @ b)))
    return float(a @ b) / norm if norm > 0.0 else 0.0


def refine_time_offset(residual_of_offset, initial_ns, span_ns=50_000_000,
                       tolerance_ns=1_000_000):
    """
    Return the offset (ns) within initial +- span that minimises residual_of_offset(ns).

    A golden-section search: the residual (e.g. the calibration's RMS residual after pairing
    with the shifted stamps) is assumed unimodal near the cross-correlation estimate.
    """
    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    low, high = initial_ns - span_ns, initial_ns + span_ns
    x1 = high - ratio * (high - low)
    x2 = low + ratio * (high - low)
    f1, f2 = residual_of_offset(int(x1)), residual_of_offset(int(x2))
    while high - low > tolerance_ns:
        if f1 <= f2:
            high, x2, f2 = x2, x1, f1
            x1 = high - ratio * (high - low)
            f1 = residual_of_offset(int(x1))
        else:
            low, x1, f1 = x1, x2, f2
            x2 = low + ratio * (high - low)
            f2 = residual_of_offset(int(x2))
    return int(round((low + high) / 2.0))


def replay_streams(link, sensor, config, sensor_offset_ns=0, runs=None):
    """
    Feed two recorded streams to a new Session in stamp order; return the session.

    link, sensor: (stamp_ns, pose.Pose) sorted by stamp (RecordedStreams, or lists); the
    session shifts the sensor stamps by sensor_offset_ns (SessionConfig.sensor_offset_ns),
    and the messages arrive in the order of the shifted stamps (a link pose first on a tie).
    The link poses between two sensor poses go to the session at once (Session.add_poses:
    the same events as one by one). runs: [(link, sensor)] of several timelines (a looped
    recording) fed one after the other instead.
    """
    session = Session(replace(config, sensor_offset_ns=sensor_offset_ns))
    for link_run, sensor_run in runs or [(link, sensor)]:
        link_run, sensor_run = RecordedStream.of(link_run), RecordedStream.of(sensor_run)
        link_stamps, sensor_stamps = link_run.stamps(), sensor_run.stamps()
        for name, run_stamps in (('link', link_stamps), ('sensor', sensor_stamps)):
            if np.any(run_stamps[1:] < run_stamps[:-1]):
                raise ValueError(f'the {name} stamps are not in order: give each timeline '
                                 'as one of `runs` (RecordedStream.runs)')
        stamps, positions, quaternions = (link_stamps.tolist(), link_run.positions(),
                                          link_run.quaternions())
        # the link poses that arrive before each sensor pose: those at or before its stamp
        before = np.searchsorted(link_stamps, sensor_stamps + sensor_offset_ns,
                                 side='right').tolist()
        fed = 0
        for index, until in enumerate(before + [len(stamps)]):
            if until > fed:
                session.add_poses(LINK, stamps[fed:until], positions[fed:until],
                                  quaternions[fed:until])
                fed = until
            if index < len(sensor_stamps):
                session.add_sensor_pose(int(sensor_stamps[index]), sensor_run.pose(index))
    return session


@dataclass(frozen=True)
class OffsetReport:
    """
    What the time-offset search found, with the residual before and after.

    runs: the timelines of the recording (its stamps started over runs - 1 times); the search
    and its residuals are of one of them (_searchable: the longest with speeds on both).
    around_ns: the known offset the search was centred on, and residual_around_deg the
    residual there (the JSON has them when the offset is not 0). A residual is None where
    the samples at that offset left nothing to solve. unaligned_ns: where the correlation
    peaked when it was below WEAK_CORRELATION (the speeds aligned nowhere within
    searched_s of around_ns, so the search started at around_ns instead), else None.
    """

    offset_ns: int
    correlation: float
    residual_without_deg: float
    residual_with_deg: float
    runs: int = 1
    around_ns: int = 0
    residual_around_deg: float = None
    unaligned_ns: int = None
    searched_s: float = 0.5

    def to_json_dict(self):
        """Return the replay JSON's `time_offset` (seconds, degrees)."""
        found = {'sensor_offset_s': self.offset_ns / NS_PER_S, 'correlation': self.correlation,
                 'residual_without_deg': finite_or_none(self.residual_without_deg),
                 'residual_with_deg': finite_or_none(self.residual_with_deg),
                 'runs': self.runs, 'speeds_aligned': self.unaligned_ns is None,
                 'searched_within_s': self.searched_s}
        if self.unaligned_ns is not None:
            found['weak_peak_s'] = self.unaligned_ns / NS_PER_S
        if self.around_ns:
            found['searched_around_s'] = self.around_ns / NS_PER_S
            found['residual_at_given_deg'] = finite_or_none(self.residual_around_deg)
        return found


def find_time_offset(link, sensor, config, max_offset_s=0.5, span_ns=50_000_000,
                     residual_options=None):
    """
    Estimate the sensor offset of two recorded streams and refine it by the residual.

    The cross-correlation estimate selects the samples once (replay_streams); the refinement
    then keeps those sensor frames and re-interpolates the link at each shifted stamp, so
    the residual is a smooth function of the offset alone. residual_options: the
    CalibrationOptions whose RMS residual scores an offset (default config.calibration).
    The search is centred on config.sensor_offset_ns (a known offset; estimate_time_offset).
    Returns (OffsetReport, the Session replayed with the refined offset applied; it estimates
    when asked, Session.estimate()). Streams whose stamps jump back by more than
    config.time_jump_ns (a looped bag, a clock restart) hold several runs: the offset is
    searched on the run with the most sensor poses of those whose two streams have an angular
    speed (poses at 3 stamps or more), and applied to all (ValueError when the
    two streams restart a different number of times); a late message within a run is put in
    its place by stamp.
    """
    residual_options = residual_options or config.calibration
    runs = _matched_runs(RecordedStream.of(link), RecordedStream.of(sensor),
                         config.time_jump_ns)
    link, sensor = max(runs, key=_searchable)
    coarse = estimate_time_offset(link.stamps(), link.quaternions(), sensor.stamps(),
                                  sensor.quaternions(), max_offset_s,
                                  centre_ns=config.sensor_offset_ns)
    peak = None
    if coarse.correlation < WEAK_CORRELATION:   # no alignment: its lag is no evidence
        peak = coarse.offset_ns
        coarse = TimeOffset(config.sensor_offset_ns, coarse.correlation)
    frames = [(sample.stamp_ns - coarse.offset_ns, sample.sensor)
              for sample in replay_streams(link, sensor, config, coarse.offset_ns).samples]
    link_at = _interpolator(link)

    @lru_cache(maxsize=None)   # each offset is a full calibration: the report asks again
    def residual(offset_ns):
        samples = [Sample(stamp + offset_ns, link_at(stamp + offset_ns), pose)
                   for stamp, pose in frames]
        samples = [s for s in samples if s.link is not None]
        try:
            return calibrate(samples, residual_options).residual_rms_deg
        except DegenerateMotionError:
            return np.inf
    offset = refine_time_offset(residual, coarse.offset_ns, span_ns)
    # Samples taken while still do not see the offset: on a flat residual the search wanders
    # in its bracket, so it only replaces the cross-correlation when it lowers the residual.
    if not residual(offset) < residual(coarse.offset_ns) * (1.0 - FLAT_RESIDUAL):
        offset = coarse.offset_ns
    session = replay_streams(link, sensor, config, offset, runs=runs)
    given = config.sensor_offset_ns
    return (OffsetReport(offset, coarse.correlation, residual(0), residual(offset), len(runs),
                         given, residual(given) if given else None, peak, max_offset_s),
            session)


def _searchable(run):
    """Rank a (link, sensor) run for the search: speeds on both streams first, then length."""
    speeds = all(len(np.unique(stream.stamps())) >= 3 for stream in run)
    return speeds, len(run[1])


def _matched_runs(link, sensor, time_jump_ns):
    """Return [(link run, sensor run)] of RecordedStream.runs, as many of each; else ValueError."""
    link_runs, sensor_runs = link.runs(time_jump_ns), sensor.runs(time_jump_ns)
    if len(link_runs) != len(sensor_runs):
        raise ValueError(f'the link stamps start over {len(link_runs) - 1} time(s) and the '
                         f'sensor stamps {len(sensor_runs) - 1} time(s): the runs cannot be '
                         'matched; drop --estimate-time-offset and give the offset '
                         '(--sensor-time-offset)')
    return list(zip(link_runs, sensor_runs))


def _interpolator(run):
    """Return pose_at(stamp_ns): a RecordedStream.at of the run, but None at its first stamp."""
    first_ns = int(run.stamps()[0]) if len(run) else None

    def pose_at(stamp_ns):
        if first_ns is None or stamp_ns <= first_ns:
            return None
        return run.at(stamp_ns)
    return pose_at
