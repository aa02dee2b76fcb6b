"""
`poses_to_bag LINK_POSES SENSOR_POSES OUT_BAG`: two pose-stream files as a bag for `replay`.

A recording exported as two files of timed poses (files/pose_streams.py: `t x y z qx qy qz
qw` a row, as the ETH hand-eye datasets and TUM trajectories are) becomes a rosbag2 of
geometry_msgs/PoseStamped on two topics, each message logged at its stamp, so that `replay`
captures samples from them, pairs their stamps and can estimate their time offset as from
any recording. The bag is written in a folder beside OUT_BAG, under OUT_BAG's name (its
storage file is named after it), and moved to OUT_BAG when complete.
"""

import argparse
import os
from pathlib import Path
import shlex
import shutil
import sys

from quatcal_ros.core.pose import Pose
from quatcal_ros.files.pose_streams import read_pose_stream
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.tools.options import HelpFormatter

EXIT_BAD_INPUT = 2
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'


def parser():
    """Return the argument parser of `poses_to_bag`."""
    parse = argparse.ArgumentParser(
        prog='poses_to_bag', formatter_class=HelpFormatter,
        description='Write two pose-stream files (rows of t x y z qx qy qz qw: seconds, '
                    'metres, a quaternion scalar last; commas or spaces; # comments) as a '
                    'rosbag2 of PoseStamped messages for replay.')
    parse.add_argument('link_poses', help="the link's poses (the robot's), one per row")
    parse.add_argument('sensor_poses', help="the sensor's poses of the object (the "
                                            "detector's), one per row")
    parse.add_argument('bag', metavar='OUT_BAG', help='the rosbag2 directory to write (it '
                                                      'must not exist)')
    parse.add_argument('--link-topic', default='/link_pose', help='default /link_pose')
    parse.add_argument('--sensor-topic', default='/sensor_pose', help='default /sensor_pose')
    parse.add_argument('--link-frame-id', default='base_link',
                       help='header.frame_id of the link poses: the frame they are given in '
                            '(the robot base); default base_link')
    parse.add_argument('--sensor-frame-id', default='camera',
                       help='header.frame_id of the sensor poses: the frame they are given in '
                            '(the sensor; the object when they are inverted); default camera')
    parse.add_argument('--storage', choices=('sqlite3', 'mcap'), default='sqlite3',
                       help='default sqlite3')
    return parse


def main(argv=None):
    """Convert; print what was written and the replay command; return the exit status."""
    args = parser().parse_args(argv)
    out = Path(args.bag)
    # rosbag2's topic names are absolute ('link_pose' played back would be relative).
    args.link_topic, args.sensor_topic = ('/' + topic.lstrip('/')
                                          for topic in (args.link_topic, args.sensor_topic))
    if args.link_topic == args.sensor_topic:
        return _fail(f'--link-topic and --sensor-topic are both {args.link_topic}')
    if os.path.lexists(out):
        return _fail(f'{out} exists: give a new directory (a bag is never written into or '
                     'over another)')
    try:
        streams = {args.link_topic: (read_pose_stream(args.link_poses), args.link_frame_id),
                   args.sensor_topic: (read_pose_stream(args.sensor_poses),
                                       args.sensor_frame_id)}
    except (BadInputError, OSError) as error:
        return _fail(str(error))
    from quatcal_ros.ros import bag   # (rosbags and the message classes only when needed)
    from quatcal_ros.ros.conversions import pose_stamped_msg
    messages = sorted(
        ((topic, stamp, order, position, quaternion, frame)
         for order, (topic, ((stamps, positions, quaternions), frame))
         in enumerate(streams.items())
         for stamp, position, quaternion in zip(stamps, positions, quaternions)),
        key=lambda m: m[1:3])   # by stamp, the link first at equal stamps
    # The bag is written as OUT_BAG's name in a folder of its own (its storage file takes
    # that name), then moved in one rename.
    partial = out.parent / f'.{out.name}.partial-{os.getpid()}'
    try:
        partial.mkdir(parents=True)
        bag.write_bag(partial / out.name, {topic: POSE_STAMPED for topic in streams}, (
            (topic, stamp, pose_stamped_msg(Pose(position, quaternion), stamp, frame,
                                            bag.TYPESTORE))
            for topic, stamp, _, position, quaternion, frame in messages), args.storage)
        os.rename(partial / out.name, out)
    except OSError as error:
        return _fail(f'{out}: cannot write: {error}')
    finally:
        shutil.rmtree(partial, ignore_errors=True)
    counts = [len(stamps) for (stamps, _, _), _ in streams.values()]
    replay = [interpreter(), '-m', 'quatcal_ros', 'replay', str(out), '--link-topic',
              args.link_topic, '--sensor-topic', args.sensor_topic]
    print(f'{out}: {counts[0]} link poses on {args.link_topic}, {counts[1]} sensor poses on '
          f'{args.sensor_topic} ({args.storage}). Replay it with:\n  {shlex.join(replay)}')
    return 0


def interpreter():
    """Return this Python as a command: relative below the working directory (.venv/...)."""
    relative = os.path.relpath(sys.executable)
    return relative if not relative.startswith('..') else sys.executable


def _fail(message):
    print(f'poses_to_bag: error: {message}', file=sys.stderr)
    return EXIT_BAD_INPUT
