"""
The board in one image: corners (sub-pixel), a planar-aware PnP, and the per-view checks.

`detect(gray, board, camera, checks)` returns a View: the board's corners in the board frame
and in the image, the pose T_camera_board and its covariance, or the named reason the view is
refused (view.REASONS). The pose comes from IPPE (OpenCV's planar PnP, which returns both
poses a plane allows) refined by Levenberg-Marquardt; when the second pose fits about as well and
points elsewhere the view is ambiguous, a marker flip waiting to happen. The covariance is
the PnP's at the pixel noise its own residuals show: sigma^2 (J^T J)^-1 with J the Jacobian
of the pixels with respect to refine.py's pose error (a rotation vector on the left in the
camera frame, then the translation), in ROS's order as Pose.covariance holds it.
"""

import cv2
import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose, ros_order
from quatcal_ros.vision.view import Checks, View


def find_corners(gray, board):
    """Return (object points (M, 3), image points (M, 2)) of the board's corners found."""
    if board.kind == 'chessboard':
        pattern = (board.size[0] - 1, board.size[1] - 1)
        found, corners = cv2.findChessboardCornersSB(gray, pattern, cv2.CALIB_CB_ACCURACY)
        if not found:
            return np.zeros((0, 3)), np.zeros((0, 2))
        return board.chessboard_points(), corners.reshape(-1, 2).astype(float)
    cv_board = board.cv_board
    if board.kind == 'charuco':
        corners, ids, _, _ = cv2.aruco.CharucoDetector(cv_board).detectBoard(gray)
        if ids is None or len(ids) == 0:
            return np.zeros((0, 3)), np.zeros((0, 2))
        points = cv_board.getChessboardCorners()[ids.ravel()]
        return points.astype(float), corners.reshape(-1, 2).astype(float)
    parameters = cv2.aruco.DetectorParameters()
    parameters.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.ArucoDetector(cv_board.getDictionary(), parameters)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None or len(ids) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2))
    object_points, image_points = cv_board.matchImagePoints(corners, ids)
    if object_points is None or len(object_points) == 0:
        return np.zeros((0, 3)), np.zeros((0, 2))
    return object_points.reshape(-1, 3).astype(float), image_points.reshape(-1, 2).astype(float)


def _no_corner(gray, board):
    """
    Say why a view gave no corner.

    A ChArUco board's markers seen alone point to its layout; markers of another dictionary
    alone, to board.yaml's dictionary.
    """
    if board.kind == 'chessboard':
        return 'no corner found'
    if board.kind == 'charuco':
        _, _, corners, ids = cv2.aruco.CharucoDetector(board.cv_board).detectBoard(gray)
        if ids is not None and len(ids):
            side = float(np.median([np.linalg.norm(c[0] - np.roll(c[0], 1, axis=0), axis=1).mean()
                                    for c in corners]))
            if side < SMALL_MARKER_PX:   # (a layout other than board.yaml's looks the same)
                return (f'{len(ids)} markers of {board.dictionary} seen, about {side:.0f} px '
                        'across, but no board corner: the board is too small in the image '
                        '(move the camera closer, or use a larger board), or its layout is not '
                        "board.yaml's (check squares_x and squares_y)")
            return (f'{len(ids)} markers of {board.dictionary} seen but no board corner: check '
                    'squares_x and squares_y, and legacy_pattern (a board printed by OpenCV '
                    'before 4.6 with an even squares_y)')
    if _markers(gray, board.dictionary) is None:
        other = _other_dictionary(gray, board.dictionary)
        if other is not None:
            return (f'no marker of {board.dictionary} seen, but {other[1]} markers of '
                    f'{other[0]}: is that the dictionary of the board (board.yaml)?')
    return 'no corner found'


# Markers smaller than this (side, pixels) rarely give ChArUco corners: the board is too far.
SMALL_MARKER_PX = 20.0
# An image whose 99th percentile of levels is below this fraction of their range is dark; one
# whose 1st percentile is above one minus it is overexposed; one whose 1st to 99th span less
# than UNIFORM of it shows nothing (a board far away on a plain wall is none of these).
EXPOSURE_LIMIT = 0.25
UNIFORM = 0.02
# The largest dictionary of each family (the smaller ones are its first ids), probed for the
# markers a view holds when the board's own dictionary sees none.
PROBED_DICTIONARIES = ('DICT_4X4_1000', 'DICT_5X5_1000', 'DICT_6X6_1000', 'DICT_7X7_1000',
                       'DICT_ARUCO_ORIGINAL', 'DICT_APRILTAG_16h5', 'DICT_APRILTAG_25h9',
                       'DICT_APRILTAG_36h10', 'DICT_APRILTAG_36h11', 'DICT_ARUCO_MIP_36h12')
# So many markers of one dictionary are no accident of texture.
MIN_PROBED_MARKERS = 4


def _exposure(gray):
    """Return '; the image is ...' when it is dark, overexposed or uniform, else ''."""
    top = np.iinfo(gray.dtype).max if np.issubdtype(gray.dtype, np.integer) else 1.0
    low, high = np.percentile(gray, (1, 99))
    levels = f'98 % of its pixels at levels {low:.0f} to {high:.0f} of {top:.0f}'
    if high < EXPOSURE_LIMIT * top:
        return f'; the image is dark ({levels}): exposure, lighting, or the lens covered?'
    if low > (1.0 - EXPOSURE_LIMIT) * top:
        return f'; the image is overexposed ({levels}): exposure or lighting?'
    if high - low < UNIFORM * top:
        return f'; the image is uniform ({levels}): is the camera seeing anything?'
    return ''


def _markers(gray, dictionary):
    """Return the ids of the markers of `dictionary` (an OpenCV name) in the image, or None."""
    detector = cv2.aruco.ArucoDetector(
        cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, dictionary)))
    ids = detector.detectMarkers(gray)[1]
    return None if ids is None or len(ids) == 0 else ids.ravel()


def _other_dictionary(gray, own):
    """Return (dictionary, markers) of the probed one that sees the most markers, or None."""
    best = None
    for name in PROBED_DICTIONARIES:
        ids = _markers(gray, name)
        if ids is None or len(ids) < MIN_PROBED_MARKERS or (best and len(ids) <= best[1]):
            continue
        if name.endswith('_1000'):   # the smallest set of the family that holds the ids
            size = next(n for n in (50, 100, 250, 1000) if ids.max() < n)
            name = f'{name[:-len("1000")]}{size}'
        if name != own:
            best = (name, len(ids))
    return best


def detect(gray, board, camera, checks=Checks()):
    """Return the View of the board in a grayscale image (module docstring)."""
    if gray is None or gray.ndim != 2 or gray.size == 0:
        return View(refused='unreadable_image', detail='not a grayscale image')
    if gray.shape != (camera.height, camera.width):
        return View(refused='wrong_image_size',
                    detail=f'{gray.shape[1]}x{gray.shape[0]} px, camera_info says '
                           f'{camera.width}x{camera.height}')
    object_points, image_points = find_corners(gray, board)
    if len(image_points) == 0:
        return View(refused='no_board', detail=_no_corner(gray, board) + _exposure(gray))
    if len(image_points) < checks.min_corners:
        return View(object_points, image_points, refused='too_few_corners',
                    detail=f'{len(image_points)} corners, at least {checks.min_corners}')
    sharpness = board_sharpness(gray, image_points)
    if sharpness < checks.min_sharpness:
        return View(object_points, image_points, sharpness=sharpness, refused='blurred',
                    detail=f'sharpness {sharpness:.1f}, at least {checks.min_sharpness:g}')
    return _with_pose(object_points, image_points, camera, checks, sharpness)


def board_sharpness(gray, image_points):
    """Return the variance of the Laplacian over the corners' bounding box."""
    x0, y0 = np.floor(image_points.min(axis=0)).astype(int)
    x1, y1 = np.ceil(image_points.max(axis=0)).astype(int)
    region = gray[max(y0, 0):y1 + 1, max(x0, 0):x1 + 1]
    if region.size < 9:
        return 0.0
    return float(cv2.Laplacian(region, cv2.CV_64F).var())


def _with_pose(object_points, image_points, camera, checks, sharpness):
    solutions = _pnp(object_points, image_points, camera)
    if not solutions:
        return View(object_points, image_points, sharpness=sharpness, refused='no_pose',
                    detail='PnP found no board pose that fits the corners with this '
                           'camera_info: check its camera matrix and distortion coefficients')
    (rvec, tvec, rms), others = solutions[0], solutions[1:]
    pose = pose_from_rvec(rvec, tvec)
    for other_rvec, other_tvec, other_rms in others:
        angle = np.degrees(quat.angle_between(pose.quaternion,
                                              pose_from_rvec(other_rvec, other_tvec).quaternion))
        if other_rms < checks.ambiguity_ratio * max(rms, 1e-3) \
                and angle > checks.ambiguity_angle_deg:
            return View(object_points, image_points, pose, rms, sharpness,
                        refused='ambiguous_pose',
                        detail=f'a second pose {angle:.1f} deg away fits with '
                               f'{other_rms:.2f} px against {rms:.2f} px')
    if rms > checks.max_reprojection_px:
        return View(object_points, image_points, pose, rms, sharpness,
                    refused='reprojection_error',
                    detail=f'RMS {rms:.2f} px, at most {checks.max_reprojection_px:g} px')
    covariance = pose_covariance(pose, object_points, image_points, camera)
    return View(object_points, image_points,
                Pose(pose.position, pose.quaternion, covariance), rms, sharpness)


def _pnp(object_points, image_points, camera):
    """Return [(rvec, tvec, RMS px)] of the finite PnP poses, best first (IPPE, LM-refined)."""
    obj = object_points.reshape(-1, 1, 3)
    img = image_points.reshape(-1, 1, 2)
    planar = np.ptp(object_points[:, 2]) < 1e-9
    flags = cv2.SOLVEPNP_IPPE if planar else cv2.SOLVEPNP_ITERATIVE
    count, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, img, camera.K, camera.D, flags=flags)
    solutions = []
    for rvec, tvec in zip(rvecs[:count], tvecs[:count]):
        rvec, tvec = cv2.solvePnPRefineLM(obj, img, camera.K, camera.D, rvec.copy(),
                                          tvec.copy())
        projected, _ = cv2.projectPoints(obj, rvec, tvec, camera.K, camera.D)
        rms = float(np.sqrt(np.mean(np.sum((projected.reshape(-1, 2) - image_points) ** 2,
                                           axis=1))))
        if np.isfinite(rms) and np.all(np.isfinite(rvec)) and np.all(np.isfinite(tvec)):
            solutions.append((rvec.ravel(), tvec.ravel(), rms))
    return sorted(solutions, key=lambda s: s[2])


def board_pose(object_points, image_points, camera):
    """Return the board's pose T_camera_board that its corners give alone (PnP), or None."""
    solutions = _pnp(object_points, image_points, camera)
    return pose_from_rvec(*solutions[0][:2]) if solutions else None


def pose_from_rvec(rvec, tvec):
    """Return the Pose of an OpenCV rotation vector and translation (T_camera_board)."""
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3))
    return Pose(np.asarray(tvec, dtype=float).reshape(3).copy(), quat.quaternion_from_matrix(R))


def pixel_jacobian(pose, object_points, camera):
    """
    Return d pixels / d (left rotation vector, translation) of T_camera_board: (2M, 6).

    Analytic: a corner c = R p + t moves by -[R p]x per rotation vector, by I per shift,
    chained with the camera's d pixels / dc.
    """
    turned = object_points @ pose.rotation.T
    _, P = camera.project_with_jacobian(turned + pose.position)      # (M, 2, 3)
    return pose_jacobian(P, turned).reshape(-1, 6)


def pose_jacobian(P, turned):
    """
    Return d pixels / d (left rotation vector, shift) of a board pose in the camera frame.

    P (..., 2, 3): the camera's d pixels / dc at each corner c = R p + t; turned: R p
    (..., 3). A row r of P times -[R p]x is -(r x R p)^T. Returns (..., 2, 6).
    """
    return np.concatenate([-np.cross(P, turned[..., None, :]), P], axis=-1)


def pose_covariance(pose, object_points, image_points, camera):
    """Return the pose's covariance (6x6, ROS order) at the pixel noise its residuals show."""
    J = pixel_jacobian(pose, object_points, camera)
    residuals = camera.project(object_points @ pose.rotation.T + pose.position) - image_points
    dof = max(residuals.size - 6, 1)
    sigma2 = max(float(np.sum(residuals ** 2)) / dof, MIN_PIXEL_NOISE ** 2)
    return ros_order(sigma2 * np.linalg.inv(J.T @ J))


# A floor of the pixel noise a covariance is computed with: a view's residuals show only the
# corners' scatter about the pose that fits them, not the errors they share (sub-pixel
# detectors are biased by about a tenth of a pixel), which a very precise view would hide.
MIN_PIXEL_NOISE = 0.1
