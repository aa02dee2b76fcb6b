"""
A camera as the calibrator's sensor: the board's pose in each image, and each sample's corners.

`ImageSensor` is what the live node (sensor_input:=image) and the bag replay (--image-topic)
share. `view(stamp_ns, gray)` detects the board (detect.py, the per-view checks) and keeps the
corners of a usable view for a while; its pose, T_camera_board with the PnP covariance, is the
session's sensor pose. When the session captures a still sample, `keep(sample)` stores that
sample's corners: the mean pixel of each board corner over the views of the still window (the
camera is still, so averaging only removes noise), or, in continuous capture, the view nearest
the sample's stamp (the session's on_sample hook calls it). `on_pixels` then refines the
pose-based estimate on those pixels (reprojection.refine_from_poses) and returns it as the
published result, method 'reprojection'.

Stamps are those of the session's sensor stream: the header stamp plus sensor_offset_ns.
"""

from collections import Counter, deque
from dataclasses import replace

import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.calibration import MIN_REFINE_SAMPLES
from quatcal_ros.core.validation import not_enough_samples, Thresholds, validate
from quatcal_ros.vision.detect import detect
from quatcal_ros.vision.reprojection import MIN_BLOCK_VIEWS, refine_from_poses, \
    VIEW_ERROR_EVIDENCE
from quatcal_ros.vision.view import Checks, View

# Each view's shared error beyond a robot's pose error (RMS per axis): the camera model or the
# board (a focal length or distortion off shows in depth), said in a warning.
ROBOT_LIKE_VIEW_ERROR_DEG = 0.5
ROBOT_LIKE_VIEW_ERROR_MM = 5.0

# Usable views kept for the next sample's corners; a still window at 30 Hz has ~15.
RECENT_VIEWS = 256
# A corner goes into a sample's mean when at least this share of the window's views saw it.
MIN_CORNER_SHARE = 0.5
# A sample keeps corners only when at least this many pass that share.
MIN_SAMPLE_CORNERS = 4


def corner_key(point):
    """Return a hashable key of a board point (micrometre grid)."""
    return tuple(np.round(np.asarray(point) * 1e6).astype(np.int64).tolist())


class ImageSensor:
    """Board detection for a session's sensor stream, and the corners of its samples."""

    def __init__(self, board, checks=Checks(), session_config=None):
        """
        Detect `board` with `checks`, for the capture of `session_config` (configure).

        :param board: vision.board.Board of the target.
        :param session_config: a stream.session.SessionConfig, or None: a 0.5 s still window,
            still capture, no sensor offset.
        """
        self.board = board
        self.checks = checks
        # A sample's views lie within half the still window either side of its stamp (the
        # middle of the window); `average`: the mean of them (still capture), else the view
        # nearest the stamp (continuous capture).
        self.half_window_ns = 250_000_000
        self.average = True
        self.sensor_offset_ns = 0
        if session_config is not None:
            self.configure(session_config)
        self.camera = None
        self.counts = Counter()          # 'images', 'detected' and each refusal's reason
        self._recent = deque(maxlen=RECENT_VIEWS)   # (stamp_ns, object points, pixels)
        self.corners = {}                # sample stamp_ns: (object points, pixels)

    def configure(self, session_config):
        """Follow a session's capture settings: its still window, mode and sensor offset."""
        capture = session_config.capture
        self.half_window_ns = capture.window_ns // 2
        self.average = capture.mode != 'continuous'
        self.sensor_offset_ns = session_config.sensor_offset_ns

    def set_camera(self, camera):
        """
        Use `camera` (vision.camera.Camera) from now on; return a sentence when it changed.

        The corners kept were measured through the old intrinsics: they are dropped, and the
        estimate goes back to the poses until new samples have corners.
        """
        old, self.camera = self.camera, camera
        if old is None or (np.allclose(old.K, camera.K, rtol=0, atol=1e-9)
                           and np.array_equal(old.D, camera.D)
                           and (old.width, old.height) == (camera.width, camera.height)):
            return ''
        samples, views = len(self.corners), len(self._recent)
        self.corners.clear()
        self._recent.clear()
        return (f'camera_info changed (new intrinsics): the corners of {samples} sample(s) and '
                f'{views} view(s) of the still window were measured with the old ones and are '
                'no longer used')

    def view(self, stamp_ns, gray):
        """Return the view.View of one image at header stamp `stamp_ns`."""
        self.counts['images'] += 1
        if self.camera is None:
            found = View(refused='no_camera_info', detail='no usable camera_info received yet')
        else:
            found = detect(gray, self.board, self.camera, self.checks)
        if found.ok:
            self.counts['detected'] += 1
            self._recent.append((stamp_ns + self.sensor_offset_ns, found.object_points,
                                 found.image_points))
        else:
            self.counts[found.refused] += 1
        return found

    def keep(self, sample):
        """Store the corners of a captured sample; return whether it has any."""
        stamp = sample.stamp_ns
        near = [v for v in self._recent if abs(v[0] - stamp) <= self.half_window_ns]
        if not near:
            return False
        if not self.average:
            near = [min(near, key=lambda v: abs(v[0] - stamp))]
        points, pixels = mean_corners([(points, pixels) for _, points, pixels in near])
        if len(points) < MIN_SAMPLE_CORNERS:   # the views saw different parts of the board
            return False
        self.corners[stamp] = points, pixels
        return True

    def restore(self, stamp_ns, points, pixels):
        """Store corners read back from a file (a resumed session)."""
        self.corners[int(stamp_ns)] = (np.asarray(points, float), np.asarray(pixels, float))

    def forget(self):
        """Forget every sample's corners and the recent views (a reset session)."""
        self.corners.clear()
        self._recent.clear()

    def restart(self):
        """Forget everything a run of the images taught: corners, views, counts, camera."""
        self.forget()
        self.counts.clear()
        self.camera = None

    def on_pixels(self, samples, result, setup, robust=True):
        """
        Return (CalibrationResult on the pixels, ReprojectionFit), or None.

        None without a camera, for a result with undetermined directions (reduced-DOF robots:
        the fit on the pixels would move along them), or with fewer than three samples with
        corners among those the result used; the fit covers the samples that have corners.
        """
        if self.camera is None or result is None or result.unobservable:
            return None   # (a robot that cannot turn freely: the pixel fit has no gauge)
        have = [i for i, sample in enumerate(samples) if sample.stamp_ns in self.corners]
        ok = [bool(result.sample_ok[i]) for i in have]
        if sum(ok) < 3:
            return None
        fit = refine_from_poses([samples[i] for i in have],
                                [self.corners[samples[i].stamp_ns] for i in have],
                                self.camera, replace(result, sample_ok=ok), setup, robust)
        views = [i for i, used in zip(have, ok) if used]   # the sample of each view fitted
        return result_on_pixels(result, fit, views), fit


def mean_corners(views):
    """Return (object points, mean pixels) of the corners most of `views` saw."""
    if len(views) == 1:
        return views[0]
    sums, counts, points = {}, Counter(), {}
    for object_points, pixels in views:
        for point, pixel in zip(object_points, pixels):
            key = corner_key(point)
            sums[key] = sums.get(key, 0.0) + pixel
            counts[key] += 1
            points[key] = point
    keys = [key for key in points if counts[key] >= MIN_CORNER_SHARE * len(views)]
    return (np.array([points[k] for k in keys], float).reshape(-1, 3),
            np.array([sums[k] / counts[k] for k in keys], float).reshape(-1, 2))


def result_on_pixels(result, fit, view_samples=None):
    """
    Return the CalibrationResult `result` with the mounting and uncertainty of `fit`.

    view_samples: the sample of each view the fit took (default: those result used); its
    "reprojection" object names the sample of the worst view (worst_view_sample).

    Its warnings say when the uncertainty is the pixel model's alone (too few views), and when
    each view's shared error is larger than a robot's.
    """
    if view_samples is None:
        view_samples = np.flatnonzero(result.sample_ok)
    views = len(fit.view_rms_px)
    few = f'with {views} views the uncertainty on the pixels is'
    later = f'from {MIN_BLOCK_VIEWS} views on it is measured over the views'
    if fit.resampled is not None:
        said = []
    elif fit.views_share_errors:
        said = [f"{few} the model's, whose errors shared by all corners of a view are fitted "
                f'to {views} views only; {later}']
    elif fit.view_error_evidence is not None and fit.view_error_evidence < VIEW_ERROR_EVIDENCE:
        said = [f"{few} the pixel noise's alone (the corners show no error that a view "
                f'shares); {later}']
    else:
        said = [f"{few} the pixel noise's alone: it leaves out errors that all corners of a "
                "view share (the robot's pose error, on real cells often several times "
                f'larger); {later}']
    said += _view_error_warning(fit, result.setup)
    if fit.focal_scale != 1.0:
        said.append(f"the corners fit camera_info's focal lengths times {fit.focal_scale:.4f} "
                    f'(+-{fit.focal_scale_sd:.2g}, a {100 * (fit.focal_scale - 1):+.1f} % '
                    f'error; likelihood-ratio evidence {fit.focal_evidence:.0f}), and the '
                    'mounting is fitted with them: calibrate the camera again (a focal '
                    "length off moves the board's depth in every view), or check board.yaml's "
                    'sizes')
    validation = pose_based = result.validation or {}
    reprojection = {**fit.to_json_dict(),
                    'worst_view_sample': int(view_samples[int(np.argmax(fit.view_rms_px))])}
    if fit.leave_one_out is not None:   # the fit on the pixels' own; the pose-based beside it
        validation = _validation_on_pixels(fit, view_samples, pose_based)
        reprojection['pose_based_validation'] = {key: pose_based.get(key) for key in (
            'verdict', 'rms_rotation_deg', 'rms_translation_mm')}
        if pose_based.get('verdict') == 'fail' and validation['verdict'] == 'pass':
            said.append('the pose-based estimate beside it fails its validation '
                        f"({pose_based['reason']}): its board poses disagree with the robot's "
                        'motions as a wrong board size or camera model makes them, which the '
                        "fit on the pixels takes up in each view's shared error (its views' "
                        f"corners {validation['rms_reprojection_px']:.2g} px from the pixels "
                        'predicted without them)')
    return replace(result, quaternion=fit.quaternion,
                   matrix=quat.matrix_from_quaternion(fit.quaternion),
                   translation=fit.translation, uncertainty_deg=fit.uncertainty_deg,
                   translation_uncertainty_mm=fit.translation_uncertainty_mm,
                   method='reprojection', warnings=[*result.warnings, *said],
                   validation=validation, reprojection=reprojection)


def _view_error_warning(fit, setup):
    """
    Return the warning of views' shared errors beyond a typical robot's pose error, or none.

    A turn of the link by ROBOT_LIKE_VIEW_ERROR_DEG also shifts the board across the line
    from the link's origin to it: by that angle times sqrt(|r|^2 - r_i^2) along camera axis i
    (r that line in the camera frame, RMS over the views; for eye-to-hand, where the link
    turns under a fixed camera, sqrt(2/3) |r| on every axis). The shift allowed on an axis
    is ROBOT_LIKE_VIEW_ERROR_MM plus that.
    """
    degrees, millimetres = np.degrees(fit.view_error[:3]), 1e3 * fit.view_error[3:]
    if setup == 'eye_to_hand':   # the board rides on the link: O = T_link_board
        lever = np.full(3, np.sqrt(2.0 / 3.0) * np.linalg.norm(fit.object_translation))
    else:   # from the link's origin (-R_X^T x_t in the camera frame) to each view's board
        r = fit.held_out.translation + fit.translation @ quat.matrix_from_quaternion(
            fit.quaternion)
        lever = np.sqrt(np.mean(np.sum(r * r, axis=1, keepdims=True) - r * r, axis=0))
    allowed = ROBOT_LIKE_VIEW_ERROR_MM + 1e3 * lever * np.radians(ROBOT_LIKE_VIEW_ERROR_DEG)
    if degrees.max() <= ROBOT_LIKE_VIEW_ERROR_DEG and np.all(millimetres <= allowed):
        return []
    return ["each view's board pose is off by up to "
            f'{degrees.max():.2g} deg and {millimetres.max():.2g} mm (RMS per axis of the camera '
            "frame) beyond the pixel noise, more than a typical robot's pose error (over "
            f'{ROBOT_LIKE_VIEW_ERROR_DEG:g} deg, or {ROBOT_LIKE_VIEW_ERROR_MM:g} mm plus what '
            f'{ROBOT_LIKE_VIEW_ERROR_DEG:g} deg of the link shifts the board by: '
            f'{" ".join(f"{v:.2g}" for v in allowed)} mm in x y z): check the camera '
            'intrinsics (camera_info: a focal length or a distortion off shows in depth, z), the '
            "board (board.yaml sizes), and the robot's poses and their stamps (a pose from "
            'another moment than the image)']


def _validation_on_pixels(fit, view_samples, pose_based):
    """
    Return the validation object of the fit on the pixels (fit.leave_one_out).

    Each view's sensor pose against the prediction of the fit without it, with the
    thresholds of the pose-based one; each sample adds reprojection_rms_px, the RMS of its
    corners from the pixels that fit predicts, and the object their RMS over the views.
    """
    thresholds = Thresholds(**pose_based.get('thresholds', {}))
    view_samples = [int(k) for k in view_samples]
    if len(view_samples) < MIN_REFINE_SAMPLES:
        return not_enough_samples(len(view_samples), MIN_REFINE_SAMPLES, thresholds, 'pixels')
    checked = validate(fit.leave_one_out, view_samples, thresholds, 'pixels')
    pixels = dict(zip(view_samples, fit.held_out.rms_px.tolist()))
    for entry in (*checked['samples'], *checked['worst']):
        entry['reprojection_rms_px'] = pixels[entry['sample']]
    return {**checked, 'rms_reprojection_px': float(np.sqrt(np.mean(fit.held_out.rms_px ** 2)))}
