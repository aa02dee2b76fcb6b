"""
The calibration in RViz: `~/markers` (visualization_msgs/MarkerArray), in the robot base frame.

After each estimate the node publishes, namespace `quatcal`:
- `sensor_axes`: the estimated sensor frame's x, y, z axes (red, green, blue arrows), where the
  latest sample puts it (eye-in-hand: link pose times mounting; eye-to-hand: the mounting);
- `uncertainty`: a cone about the sensor's z axis whose half-angle is three times the
  rotation uncertainty (at least 0.5 deg, to stay visible), and a sphere whose radius is three
  times the translation uncertainty, at the sensor's origin;
- `samples`: the link position of every sample (green used, orange down-weighted, red
  rejected);
- `next_pose`: the planner's proposal, an arrow along the proposed link's z axis and its label.
On ~/reset one DELETEALL clears them. Lengths in metres.
"""

from geometry_msgs.msg import Point
import numpy as np
from quatcal_ros.core.pose import Pose
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

NAMESPACE = 'quatcal'
AXIS_LENGTH_M = 0.1
CONE_LENGTH_M = 0.15
CONE_SIDES = 24
MIN_CONE_DEG = 0.5
MAX_CONE_DEG = 80.0   # a cone of 90 deg or more has no rim in front of the sensor
SIGMAS = 3.0
COLOURS = {'x': (0.9, 0.1, 0.1, 1.0), 'y': (0.1, 0.8, 0.1, 1.0), 'z': (0.1, 0.3, 0.95, 1.0),
           'used': (0.1, 0.75, 0.2, 1.0), 'noisy': (1.0, 0.6, 0.0, 1.0),
           'rejected': (0.95, 0.1, 0.1, 1.0), 'cone': (0.1, 0.3, 0.95, 0.25),
           'sphere': (0.6, 0.6, 0.6, 0.35), 'next': (0.8, 0.2, 0.9, 1.0)}


def _colour(name):
    r, g, b, a = COLOURS[name]
    return ColorRGBA(r=r, g=g, b=b, a=a)


def _point(xyz):
    x, y, z = (float(v) for v in xyz)
    return Point(x=x, y=y, z=z)


def _points(rows):
    """Return geometry_msgs/Point of each row of an (N, 3) array (the sample dots, the cone)."""
    return [Point(x=x, y=y, z=z) for x, y, z in np.asarray(rows, float).tolist()]


def _marker(header, name, index, kind, colour, scale=(1.0, 1.0, 1.0)):
    marker = Marker(header=header, ns=NAMESPACE, id=index, type=kind, action=Marker.ADD)
    marker.pose.orientation.w = 1.0
    marker.scale.x, marker.scale.y, marker.scale.z = (float(v) for v in scale)
    marker.color = _colour(colour)
    marker.text = name
    return marker


def sensor_pose_in_base(result, samples, setup):
    """Return the sensor's pose in the base frame (latest sample's link for eye-in-hand)."""
    mounting = Pose.create(result.translation, result.quaternion)
    if setup == 'eye_to_hand' or not samples:
        return mounting
    return samples[-1].link @ mounting


def calibration_markers(result, samples, states, next_pose, setup, header):
    """
    Return the MarkerArray of the module docstring.

    states: 'used', 'noisy' or 'rejected' per sample; next_pose: core.planner.NextPose or
    None; header: std_msgs/Header (base frame, stamp) of every marker.
    """
    sensor = sensor_pose_in_base(result, samples, setup)
    R, origin = sensor.rotation, sensor.position
    markers = []
    for k, axis in enumerate('xyz'):
        arrow = _marker(header, f'sensor {axis}', k, Marker.ARROW, axis, (0.006, 0.012, 0.02))
        arrow.points = [_point(origin), _point(origin + AXIS_LENGTH_M * R[:, k])]
        markers.append(arrow)
    markers.append(_cone(header, 3, origin, R, result.uncertainty_deg))
    radius = max(SIGMAS * result.translation_uncertainty_mm * 1e-3, 1e-4)
    sphere = _marker(header, 'translation uncertainty', 4, Marker.SPHERE, 'sphere',
                     (2 * radius,) * 3)
    sphere.pose.position = _point(origin)
    markers.append(sphere)
    dots = _marker(header, 'samples', 5, Marker.SPHERE_LIST, 'used', (0.015,) * 3)
    dots.points = _points([s.link.position for s in samples])
    palette = {state: _colour(state) for state in set(states)}
    dots.colors = [palette[state] for state in states]
    markers.append(dots)
    if next_pose is not None:
        link = next_pose.link
        arrow = _marker(header, 'next pose', 6, Marker.ARROW, 'next', (0.008, 0.016, 0.025))
        arrow.points = [_point(link.position),
                        _point(link.position + AXIS_LENGTH_M * link.rotation[:, 2])]
        label = _marker(header, 'next pose', 7, Marker.TEXT_VIEW_FACING, 'next',
                        (0.0, 0.0, 0.03))
        label.pose.position = _point(link.position + np.array([0.0, 0.0, 0.04]))
        markers += [arrow, label]
    return MarkerArray(markers=markers)


def _cone(header, index, origin, R, uncertainty_deg):
    """Return a TRIANGLE_LIST cone from the sensor's origin about its z axis."""
    half = np.radians(min(max(SIGMAS * uncertainty_deg, MIN_CONE_DEG), MAX_CONE_DEG))
    radius = CONE_LENGTH_M * np.tan(half)
    angles = np.linspace(0.0, 2 * np.pi, CONE_SIDES + 1)
    rim = origin + np.column_stack([radius * np.cos(angles), radius * np.sin(angles),
                                    np.full(len(angles), CONE_LENGTH_M)]) @ R.T
    cone = _marker(header, 'rotation uncertainty', index, Marker.TRIANGLE_LIST, 'cone')
    triangles = np.stack([np.repeat(origin[None], CONE_SIDES, axis=0), rim[:-1], rim[1:]], axis=1)
    cone.points = _points(triangles.reshape(-1, 3))
    return cone


def clear_markers(header):
    """Return the MarkerArray that deletes every marker (~/reset)."""
    return MarkerArray(markers=[Marker(header=header, ns=NAMESPACE, action=Marker.DELETEALL)])
