"""
Calibration targets (DESIGN.md contract 5, board.yaml): what the board is and its corners.

    type: charuco | aruco_grid | chessboard | apriltag_grid
    squares_x, squares_y            (charuco, chessboard: squares along x and y)
    markers_x, markers_y            (aruco_grid, apriltag_grid)
    square_length_m, marker_length_m, marker_separation_m (grids)
    dictionary                      an OpenCV name, e.g. DICT_5X5_100, DICT_APRILTAG_36h11

The board frame is OpenCV's for each type (origin at a board corner, z out of the board for
ChArUco and grids; the chessboard's inner-corner grid for chessboards). Errors name the file
and the field.
"""

from dataclasses import dataclass

import cv2
import numpy as np
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.text_input import BadInputError

TYPES = ('charuco', 'aruco_grid', 'chessboard', 'apriltag_grid')
MAX_LENGTH_M = 5.0
MIN_LENGTH_M = 1e-4   # 0.1 mm: below any printed board (OpenCV fails on 1e-300 with SystemError)


@dataclass(frozen=True)
class Board:
    """A calibration target and the OpenCV objects that find it."""

    kind: str                   # a TYPES entry
    size: tuple                 # squares (charuco, chessboard) or markers (grids), x and y
    square_length_m: float      # charuco, chessboard
    marker_length_m: float      # charuco, grids
    marker_separation_m: float  # grids
    dictionary: str
    legacy_pattern: bool = False   # charuco: the layout of OpenCV before 4.6 (even squares_y)

    @property
    def cv_board(self):
        """Return the cv2.aruco board (None for a chessboard)."""
        if self.kind == 'chessboard':
            return None
        dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, self.dictionary))
        if self.kind == 'charuco':
            board = cv2.aruco.CharucoBoard(self.size, self.square_length_m,
                                           self.marker_length_m, dictionary)
            board.setLegacyPattern(self.legacy_pattern)
            return board
        return cv2.aruco.GridBoard(self.size, self.marker_length_m, self.marker_separation_m,
                                   dictionary)

    def chessboard_points(self):
        """Return the chessboard's inner corners (K, 3) in the board frame, OpenCV's order."""
        nx, ny = self.size[0] - 1, self.size[1] - 1
        grid = np.mgrid[0:nx, 0:ny].T.reshape(-1, 2) * self.square_length_m
        return np.hstack([grid, np.zeros((len(grid), 1))])

    @property
    def extent_m(self):
        """Return the board's width and height in metres."""
        if self.kind in ('charuco', 'chessboard'):
            return self.size[0] * self.square_length_m, self.size[1] * self.square_length_m
        step = self.marker_length_m + self.marker_separation_m
        return (self.size[0] * step - self.marker_separation_m,
                self.size[1] * step - self.marker_separation_m)


def read_board(path):
    """Read board.yaml; raise BadInputError naming the file and field."""
    return parse_board(plain_yaml.load_file(path, holds='a board file'), str(path))


def parse_board(document, name='<board>'):
    """Return the Board a board.yaml document describes."""
    if not isinstance(document, dict):
        raise BadInputError(f'{name}: expected a mapping with type, sizes and lengths')
    kind = document.get('type')
    if kind not in TYPES:
        raise BadInputError(f'{name}, field type: {kind!r} is not one of {", ".join(TYPES)}')
    squares = kind in ('charuco', 'chessboard')
    count_names = ('squares_x', 'squares_y') if squares else ('markers_x', 'markers_y')
    size = tuple(_count(document, field, name) for field in count_names)
    square = _length(document, 'square_length_m', name) if squares else 0.0
    marker = _length(document, 'marker_length_m', name) if kind != 'chessboard' else 0.0
    separation = (_length(document, 'marker_separation_m', name)
                  if kind in ('aruco_grid', 'apriltag_grid') else 0.0)
    if kind == 'chessboard' and sum(size) % 2 == 0:   # turned half round, it looks the same
        raise BadInputError(f'{name}, field squares_y: a chessboard of {size[0]} x {size[1]} '
                            'squares looks the same turned by 180 degrees, so its corners have '
                            'two orders and its pose can flip: use one even and one odd count '
                            '(e.g. 9 x 6)')
    if kind == 'charuco' and not marker < square:
        raise BadInputError(f'{name}, field marker_length_m: {marker:g} m must be smaller '
                            f'than square_length_m ({square:g} m)')
    dictionary = ''
    if kind != 'chessboard':
        default = 'DICT_APRILTAG_36h11' if kind == 'apriltag_grid' else None
        dictionary = document.get('dictionary', default)
        if not (isinstance(dictionary, str) and dictionary.startswith('DICT_')
                and hasattr(cv2.aruco, dictionary)):
            raise BadInputError(f'{name}, field dictionary: {dictionary!r} is not an OpenCV '
                                'dictionary name (e.g. DICT_5X5_100, DICT_APRILTAG_36h11)')
    legacy = document.get('legacy_pattern', False)
    if not isinstance(legacy, bool):
        raise BadInputError(f'{name}, field legacy_pattern: {legacy!r} is not true or false')
    if legacy and kind != 'charuco':
        raise BadInputError(f'{name}, field legacy_pattern: only a charuco board has one')
    board = Board(kind, size, square, marker, separation, dictionary, legacy)
    if kind != 'chessboard':
        needed = (size[0] * size[1] // 2 if kind == 'charuco' else size[0] * size[1])
        available = cv2.aruco.getPredefinedDictionary(
            getattr(cv2.aruco, dictionary)).bytesList.shape[0]
        if needed > available:
            raise BadInputError(f'{name}, field dictionary: {dictionary} has {available} '
                                f'markers; the board needs {needed}')
    return board


def _count(document, field, name):
    value = document.get(field)
    if not isinstance(value, int) or isinstance(value, bool) or not 2 <= value <= 100:
        raise BadInputError(f'{name}, field {field}: {value!r} is not a count from 2 to 100')
    return value


def _length(document, field, name):
    value = document.get(field)
    if isinstance(value, bool) or not isinstance(value, (int, float)) \
            or not MIN_LENGTH_M <= value <= MAX_LENGTH_M:
        raise BadInputError(f'{name}, field {field}: {value!r} is not a length in metres '
                            f'({MIN_LENGTH_M:g} to {MAX_LENGTH_M:g})')
    return float(value)
