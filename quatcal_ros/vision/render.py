"""
Rendered views of a calibration target from a known camera: test and benchmark images.

`Renderer(board, camera)` draws the board flat once, finds the homography from the board
plane (metres, board frame) to that drawing from the corners OpenCV itself detects in it (so
it holds for every board type and OpenCV version), and renders any pose T_camera_board by a
perspective warp of that drawing (pinhole, distortion-free cameras), supersampled 2x, on a
grey background, with optional blur, pixel noise and a brightness change. `view_poses` draws
poses with the board in front of the camera; `write_dataset` writes DESIGN.md contract 5's
folder.
"""

import csv
from pathlib import Path

import cv2
import numpy as np
from quatcal_ros.core import quaternion as quat
from quatcal_ros.core.pose import Pose
from quatcal_ros.vision.detect import find_corners

FLAT_PX_PER_M = 8000.0
SUPERSAMPLE = 2
BACKGROUND = 110


class Renderer:
    """Draws one board as a given camera sees it."""

    def __init__(self, board, camera):
        self.board = board
        self.camera = camera
        self.flat, self.plane_to_flat = _flat_board(board)
        # The board's front: facing a camera unmirrored. When the drawing maps the board's x, y
        # to pixels without a mirror, the board faces a camera whose axes it shares (z away
        # from the camera); else it is turned half a turn about its x axis.
        mirrored = np.linalg.det(self.plane_to_flat[:2, :2]) < 0
        self.facing = (quat.from_rotation_vector([np.pi, 0, 0]) if mirrored
                       else quat.IDENTITY.copy())

    def render(self, T_camera_board, rng=None, noise=0.0, blur_sigma=0.0, gain=1.0):
        """Return the grayscale image (uint8) of the board at pose T_camera_board."""
        R, t = T_camera_board.rotation, T_camera_board.position
        plane_to_camera = self.camera.K @ np.column_stack([R[:, 0], R[:, 1], t])
        scale = np.diag([SUPERSAMPLE, SUPERSAMPLE, 1.0])
        # Pixel centres: a supersampled pixel (i + 0.5) / s - 0.5 of the image.
        shift = np.array([[1, 0, 0.5 * (SUPERSAMPLE - 1)], [0, 1, 0.5 * (SUPERSAMPLE - 1)],
                          [0, 0, 1]])
        M = shift @ scale @ plane_to_camera @ np.linalg.inv(self.plane_to_flat)
        size = (self.camera.width * SUPERSAMPLE, self.camera.height * SUPERSAMPLE)
        big = cv2.warpPerspective(self.flat, M, size, flags=cv2.INTER_LINEAR,
                                  borderMode=cv2.BORDER_CONSTANT, borderValue=BACKGROUND)
        image = cv2.resize(big, (self.camera.width, self.camera.height),
                           interpolation=cv2.INTER_AREA).astype(float) * gain
        if blur_sigma > 0:
            image = cv2.GaussianBlur(image, (0, 0), blur_sigma)
        if noise > 0:
            image = image + (rng or np.random.default_rng()).normal(0.0, noise, image.shape)
        return np.clip(np.round(image), 0, 255).astype(np.uint8)


def _flat_board(board):
    """Return the board drawn flat (uint8) and the homography board plane (m) -> its pixels."""
    width_m, height_m = board.extent_m
    margin_px = int(0.08 * FLAT_PX_PER_M * min(width_m, height_m)) + 20
    size = (int(width_m * FLAT_PX_PER_M) + 2 * margin_px,
            int(height_m * FLAT_PX_PER_M) + 2 * margin_px)
    if board.kind == 'chessboard':   # whole-pixel squares: the homography is exact
        square = int(round(board.square_length_m * FLAT_PX_PER_M))
        size = (board.size[0] * square + 2 * margin_px, board.size[1] * square + 2 * margin_px)
        flat = np.full((size[1], size[0]), 255, np.uint8)
        for i in range(board.size[0]):
            for j in range(board.size[1]):
                if (i + j) % 2 == 0:
                    flat[margin_px + j * square:margin_px + (j + 1) * square,
                         margin_px + i * square:margin_px + (i + 1) * square] = 0
        # Inner corner (k, l) lies between pixels: at margin + (k + 1) square - 0.5.
        scale = square / board.square_length_m
        offset = margin_px + square - 0.5
        drawing = np.array([[scale, 0, offset], [0, scale, offset], [0, 0, 1.0]])
        return flat, drawing @ _detector_order(flat, board, drawing)
    flat = board.cv_board.generateImage(size, marginSize=margin_px)
    object_points, image_points = find_corners(flat, board)
    if len(object_points) < 4:
        raise RuntimeError(f'the flat {board.kind} board is not found in its own drawing')
    H, _ = cv2.findHomography(object_points[:, :2], image_points)
    return flat, H


def _detector_order(flat, board, drawing):
    """
    Return the exact plane map (3x3) from the detector's board frame to the drawing's.

    OpenCV numbers a chessboard's corners from a corner it chooses; the board frame is that
    numbering's, so the exact drawing homography is composed with the (whole-square) turn or
    flip that takes the detected order to the drawn one.
    """
    object_points, image_points = find_corners(flat, board)
    drawn = cv2.perspectiveTransform(image_points.reshape(-1, 1, 2),
                                     np.linalg.inv(drawing)).reshape(-1, 2)
    affine, _ = cv2.estimateAffine2D(np.ascontiguousarray(object_points[:, :2]), drawn)
    step = board.square_length_m
    turn = np.round(affine[:, :2])                     # a whole turn or flip: entries 0, +-1
    shift = np.round(affine[:, 2] / step) * step       # whole squares
    return np.vstack([np.column_stack([turn, shift]), [0, 0, 1.0]])


def view_poses(rng, n, renderer, distance_m=(0.35, 0.7), tilt_deg=35.0, offset_m=0.05):
    """
    Return n poses T_camera_board with the board in front of the camera, facing it.

    The board's centre lies near the optical axis (within offset_m) at distance_m; the board
    is tilted by up to tilt_deg about a random axis and turned about the optical axis.
    """
    board = renderer.board
    width_m, height_m = board.extent_m
    centre = np.array([width_m / 2, height_m / 2, 0.0])
    poses = []
    for _ in range(n):
        axis = rng.normal(size=3)
        axis[2] = 0.0
        axis /= np.linalg.norm(axis)
        tilt = quat.from_rotation_vector(axis * np.radians(rng.uniform(0, tilt_deg)))
        spin = quat.from_rotation_vector([0, 0, rng.uniform(-np.pi / 4, np.pi / 4)])
        q = quat.multiply(tilt, quat.multiply(spin, renderer.facing))
        R = quat.matrix_from_quaternion(q)
        target = np.array([*rng.uniform(-offset_m, offset_m, 2), rng.uniform(*distance_m)])
        poses.append(Pose(target - R @ centre, q))
    return poses


def cell_views(rng, renderer, n, distance_m=(0.3, 0.9)):
    """
    Return an eye-in-hand cell seen n times: (mounting X, board pose O, views, link poses).

    X (T_link_camera) and O (T_base_board) are random; the views T_camera_board come from
    view_poses; link pose i is the T_base_link that sees view i: O inv(S_i) inv(X).
    """
    mounting = Pose.create([0.05, -0.03, 0.08], quat.from_rotation_vector(rng.normal(size=3)))
    board = Pose.create([0.6, 0.1, 0.0], quat.from_rotation_vector(rng.normal(size=3)))
    seen = view_poses(rng, n, renderer, distance_m=distance_m)
    return mounting, board, seen, [board @ s.inverse() @ mounting.inverse() for s in seen]


def write_dataset(folder, board_document, camera, names, link_poses, images):
    """Write DESIGN.md contract 5's folder: images/, robot_poses.csv, camera_info.yaml, board."""
    from quatcal_ros.files import plain_yaml
    folder = Path(folder)
    (folder / 'images').mkdir(parents=True, exist_ok=True)
    for name, image in zip(names, images):
        cv2.imwrite(str(folder / 'images' / name), image)
    with open(folder / 'robot_poses.csv', 'w', newline='') as stream:
        writer = csv.writer(stream)
        writer.writerow(['image', 'link_x', 'link_y', 'link_z', 'link_qx', 'link_qy', 'link_qz',
                         'link_qw'])
        for name, pose in zip(names, link_poses):
            w, x, y, z = pose.quaternion
            writer.writerow([name, *(repr(float(v)) for v in (*pose.position, x, y, z, w))])
    info = {'image_width': camera.width, 'image_height': camera.height,
            'camera_name': 'rendered',
            'camera_matrix': {'rows': 3, 'cols': 3, 'data': camera.K.ravel().tolist()},
            'distortion_model': camera.distortion_model,
            'distortion_coefficients': {'rows': 1, 'cols': len(camera.D),
                                        'data': camera.D.tolist()}}
    for name, content in (('camera_info.yaml', info), ('board.yaml', board_document)):
        (folder / name).write_text(plain_yaml.dump(content, sort_keys=False), encoding='utf-8')
