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

    def __post_init__(self):
        """Raise ValueError naming a check no view can pass or that OpenCV cannot run."""
        if not self.min_corners >= 4:   # a planar PnP needs 4 points (OpenCV asserts it)
            raise ValueError(f'min_corners must be at least 4 (a board pose needs 4 '
                             f'corners), not {self.min_corners}')
        for name in ('max_reprojection_px', 'ambiguity_ratio', 'ambiguity_angle_deg'):
            if not getattr(self, name) > 0.0:   # (NaN fails too)
                raise ValueError(f'{name} must be positive, not {getattr(self, name)}')
        if not self.min_sharpness >= 0.0:
            raise ValueError(f'min_sharpness must be 0 or more, not {self.min_sharpness}')


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
