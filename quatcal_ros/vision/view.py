"""
What one image gave: the View of the board (or why none) and the Checks a view must pass.

Plain types without OpenCV, so the paths that only count and report views (the replay and
the node's image input) load no cv2 until an image is detected (detect.py).
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.core.pose import Pose

REASONS = {
    'unreadable_image': 'the file is not an image OpenCV can read',
    'wrong_image_size': 'the image size differs from camera_info',
    'no_board': 'no corner of the board was found',
    'too_few_corners': 'fewer corners than a reliable pose needs',
    'blurred': 'the board region is too blurred (sharpness below the threshold)',
    'no_pose': 'no board pose fits the corners with this camera_info (PnP found none)',
    'ambiguous_pose': 'two board poses fit about equally well (planar ambiguity)',
    'reprojection_error': 'the pose leaves corner residuals above the threshold',
}


@dataclass(frozen=True)
class Checks:
    """What a view must satisfy to be used."""

    min_corners: int = 8
    max_reprojection_px: float = 2.0
    min_sharpness: float = 10.0          # variance of the Laplacian over the board region
    ambiguity_ratio: float = 1.2         # second PnP pose's RMS within this factor: ambiguous
    ambiguity_angle_deg: float = 3.0     # ... and this far from the first


@dataclass(frozen=True)
class View:
    """One image's detection: corners, pose, quality, or why it is refused."""

    object_points: np.ndarray = None     # (M, 3) board frame, metres
    image_points: np.ndarray = None      # (M, 2) pixels
    pose: Pose = None                    # T_camera_board, with its covariance (ROS order)
    rms_px: float = float('nan')
    sharpness: float = float('nan')
    refused: str = ''                    # a key of REASONS, or ''
    detail: str = ''

    @property
    def ok(self):
        return not self.refused
