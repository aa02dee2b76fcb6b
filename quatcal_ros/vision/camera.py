"""
The camera model: camera_calibration's YAML (DESIGN.md contract 5) or a sensor_msgs CameraInfo.

Intrinsics K (3x3) and distortion as ROS names them: plumb_bob (k1, k2, p1, p2, k3) and
rational_polynomial (k1, k2, p1, p2, k3, k4, k5, k6), the orders OpenCV takes. `project` is
OpenCV's model in numpy (checked against cv2.projectPoints), so a refinement can evaluate
every corner of every view at once.
"""

from dataclasses import dataclass

import numpy as np
from quatcal_ros.files import plain_yaml
from quatcal_ros.files.text_input import BadInputError, read_text

MODELS = {'plumb_bob': 5, 'rational_polynomial': 8}


@dataclass(frozen=True)
class Camera:
    """Image size, intrinsics and distortion of one camera."""

    width: int
    height: int
    K: np.ndarray            # 3x3
    distortion_model: str
    D: np.ndarray            # 5 or 8 coefficients, OpenCV's order

    def project(self, points):
        """Return the pixels (..., 2) of camera-frame points (..., 3) (z > 0)."""
        return self._projected(points, derivatives=False)[0]

    def project_with_jacobian(self, points):
        """Return the pixels (..., 2) of points (..., 3) and d pixels / d point (..., 2, 3)."""
        return self._projected(points, derivatives=True)

    def _projected(self, points, derivatives):
        p = np.asarray(points, dtype=float)
        inverse_z = 1.0 / p[..., 2]
        x, y = p[..., 0] * inverse_z, p[..., 1] * inverse_z
        d = np.zeros(8)
        d[:len(self.D)] = self.D
        k1, k2, p1, p2, k3, k4, k5, k6 = d
        r2 = x * x + y * y
        numerator = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        denominator = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
        radial = numerator / denominator
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        K = self.K
        pixels = np.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]],
                          axis=-1)
        if not derivatives:
            return pixels, None
        # d radial / d r2 by the quotient rule, then the distorted point's 2 x 2 Jacobian
        slope = ((k1 + r2 * (2 * k2 + 3 * k3 * r2)) * denominator
                 - numerator * (k4 + r2 * (2 * k5 + 3 * k6 * r2))) / denominator ** 2
        cross = 2 * x * y * slope + 2 * p1 * x + 2 * p2 * y          # d xd/dy = d yd/dx
        distorted = np.stack([
            np.stack([radial + 2 * x * x * slope + 2 * p1 * y + 6 * p2 * x, cross], axis=-1),
            np.stack([cross, radial + 2 * y * y * slope + 6 * p1 * y + 2 * p2 * x], axis=-1)],
            axis=-2)                                                 # (..., 2, 2)
        # (x, y) = (X, Y) / Z: d (x, y) / d (X, Y, Z)
        zero = np.zeros_like(x)
        normalised = np.stack([np.stack([inverse_z, zero, -x * inverse_z], axis=-1),
                               np.stack([zero, inverse_z, -y * inverse_z], axis=-1)], axis=-2)
        return pixels, K[:2, :2] @ distorted @ normalised


def read_camera_yaml(path):
    """Read camera_calibration's YAML; raise BadInputError naming the file and field."""
    text = read_text(path, plain_yaml.MAX_CHARACTERS)
    if text.startswith('%YAML:1.0'):   # PyYAML's message did not name the format
        raise BadInputError(f'{path}: an OpenCV FileStorage file (%YAML:1.0), not ROS '
                            "camera_calibration's YAML (image_width, image_height, "
                            'camera_matrix: {rows, cols, data}, distortion_model, '
                            'distortion_coefficients)')
    return parse_camera(plain_yaml.load(text, str(path), holds='a camera_info file'), str(path))


def parse_camera(document, name='<camera_info>'):
    """Return the Camera of a camera_calibration document (a mapping)."""
    if not isinstance(document, dict):
        raise BadInputError(f'{name}: expected the mapping camera_calibration writes '
                            '(image_width, camera_matrix, distortion_model, '
                            'distortion_coefficients)')
    width, height = (_size(document, field, name) for field in ('image_width', 'image_height'))
    K = _matrix(document, 'camera_matrix', name, (3, 3))
    model = document.get('distortion_model', 'plumb_bob')
    if not isinstance(model, str) or model not in MODELS:   # (a list raised a TypeError)
        raise BadInputError(f'{name}, field distortion_model: {_unknown_model(model)}')
    D = _matrix(document, 'distortion_coefficients', name, None).ravel()
    return camera_from(width, height, K, model, D, name)


def _unknown_model(model):
    """Say that distortion model `model` is not one this tool reads, and what to do."""
    fisheye = (': fisheye lenses are not supported; give rectified images with zero '
               'distortion and the rectified camera matrix (P)'
               if model in ('equidistant', 'fisheye', 'kannala_brandt') else '')
    return f'{model!r} is not one of {", ".join(MODELS)}{fisheye}'


def camera_from(width, height, K, model, D, name='camera_info'):
    """Return a checked Camera (also for a CameraInfo message's fields)."""
    K = np.asarray(K, dtype=float).reshape(3, 3)
    D = np.asarray(D, dtype=float).ravel()
    if not (width > 0 and height > 0):   # (it was blamed on the camera matrix)
        raise BadInputError(f'{name}: image size {width}x{height} px: not the size of a '
                            'calibrated camera (width and height unset?)')
    if model not in MODELS:
        raise BadInputError(f'{name}: distortion_model {_unknown_model(model)}')
    if len(D) != MODELS[model]:
        if not (model == 'plumb_bob' and len(D) in (4, 5)):
            raise BadInputError(f'{name}, field distortion_coefficients: {model} takes '
                                f'{MODELS[model]} coefficients, not {len(D)}')
    for field, values in (('camera_matrix', K), ('distortion_coefficients', D)):
        if not np.all(np.isfinite(values)):
            raise BadInputError(f'{name}, field {field}: NaN or inf')
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0 and 0 <= cx <= width and 0 <= cy <= height
            and K[2, 2] == 1 and not K[1, 0] and not K[2, 0] and not K[2, 1]):
        raise BadInputError(f'{name}, field camera_matrix: not a camera matrix (fx, fy > 0, '
                            'the principal point inside the image, last row 0 0 1); an '
                            'all-zero CameraInfo means the camera is not calibrated')
    if abs(K[0, 1]) > 1e-9 * fx:   # 3 px of skew moved every view's pose by 0.8 degrees
        raise BadInputError(f'{name}, field camera_matrix: skew {K[0, 1]:g} px (K[0][1]): '
                            "OpenCV's board pose ignores skew; calibrate the camera without it "
                            '(ROS camera_calibration never fits one)')
    return Camera(int(width), int(height), K, model, D)


def _size(document, field, name):
    value = document.get(field)
    if not isinstance(value, int) or isinstance(value, bool) or not 0 < value <= 100_000:
        raise BadInputError(f'{name}, field {field}: {value!r} is not an image size in pixels')
    return value


def _matrix(document, field, name, shape):
    value = document.get(field)
    data = value.get('data') if isinstance(value, dict) else None
    try:
        array = np.array(data, dtype=float)
    except (TypeError, ValueError):
        array = None
    if array is None or array.ndim != 1 or (shape and array.size != shape[0] * shape[1]):
        raise BadInputError(f'{name}, field {field}: expected {{rows, cols, data: [...]}} '
                            f'with {shape[0] * shape[1] if shape else "the"} numbers')
    rows, cols = (_whole(value.get(key)) for key in ('rows', 'cols'))
    if value.get('rows') is not None and value.get('cols') is not None and (
            rows is None or cols is None or rows * cols != array.size
            or (shape and (rows, cols) != tuple(shape))):
        # (a file edited by hand: the numbers may not be the ones meant)
        raise BadInputError(f'{name}, field {field}: rows {value["rows"]!r} and cols '
                            f'{value["cols"]!r} do not '
                            f'describe its {array.size} numbers'
                            + (f' (a {shape[0]}x{shape[1]} matrix)' if shape else ''))
    return array.reshape(shape) if shape else array


def _whole(number):
    """Return `number` as an int when it is a whole number (3 or 3.0), else None."""
    if isinstance(number, bool) or not isinstance(number, (int, float)):
        return None
    return int(number) if float(number).is_integer() else None
