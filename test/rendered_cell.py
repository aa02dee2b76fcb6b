"""The rendered camera cell of the image tests: one ChArUco board and one camera."""

from quatcal_ros.files import plain_yaml
from quatcal_ros.vision.camera import camera_from

BOARD = {'type': 'charuco', 'squares_x': 7, 'squares_y': 5, 'square_length_m': 0.03,
         'marker_length_m': 0.022, 'dictionary': 'DICT_5X5_100'}
CAMERA = camera_from(640, 480, [[600, 0, 320], [0, 600, 240], [0, 0, 1]], 'plumb_bob',
                     [0, 0, 0, 0, 0])


def write_board(folder):
    """Write BOARD as folder/board.yaml; return its path."""
    path = folder / 'board.yaml'
    path.write_text(plain_yaml.dump(BOARD))
    return path


def camera_info_msg(camera=CAMERA):
    """Return the sensor_msgs/CameraInfo (rclpy) of a vision.camera.Camera."""
    from quatcal_ros.ros.conversions import camera_info_msg as of_camera
    return of_camera(camera)
