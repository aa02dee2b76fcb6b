"""
Command-line tools of DESIGN.md contract 3 that run without ROS: `solve` and `replay`.

Exit status: 0 success; 2 bad input or arguments (stderr names file, row and field, or bag
and topic); 3 the data cannot determine the rotation (stderr says why and what motion would
help).  `replay` drives the same session.Session as the live node, fed from a rosbag2
recording by quatcal_ros.ros.bag.
"""

import argparse
from dataclasses import replace
import json
from pathlib import Path
import sys
import time

from quatcal_ros.core.planner import plan_next_pose, PlanLimits
from quatcal_ros.core.units import DO_NOT_USE, NS_PER_S
from quatcal_ros.core.validation import failure_warning, published
from quatcal_ros.files import bag_folder, exports
from quatcal_ros.files import importers
from quatcal_ros.files.journal import absolute, JournalHeader, JournalRefused
from quatcal_ros.files.persistence import atomic_write_text
from quatcal_ros.files.samples_csv import format_samples
from quatcal_ros.files.session_record import MoveWatch, SamplesJournal, save_result
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.stream import tf_joint
from quatcal_ros.stream.arrival_lag import APART_NS, stamps_apart
from quatcal_ros.stream.capture import JUMP_BANDS, unsteady_sensor_note
from quatcal_ros.stream.recorded_stream import RecordedStream
from quatcal_ros.stream.session import Rejected, Session
from quatcal_ros.stream.settings import check_config, ConfigError, IMAGES_NOT_INVERTED, \
    plan_limits, session_config
from quatcal_ros.stream.tf_tree import frame_problem, normalize_frame
from quatcal_ros.stream.time_offset import find_time_offset, link_speed_deg_s
from quatcal_ros.tools.options import add_setting_options, HelpFormatter, settings_of
from quatcal_ros.tools.output_paths import output_problem
from quatcal_ros.tools.progress import Progress

EXIT_BAD_INPUT = 2
EXIT_UNDETERMINED = 3
EXIT_INTERRUPTED = 130


ESTIMATOR = ('setup', 'pairs', 'robust', 'invert_sensor', 'method', 'min_motion_deg',
             'validation_max_rotation_deg', 'validation_max_translation_mm',
             'plan_max_rotation_deg', 'plan_view_cone_deg', 'plan_workspace_margin_m',
             'known_translation')


def solve_main(argv=None):
    """`solve SAMPLES`: estimate the mounting from a samples file, print JSON."""
    parser = argparse.ArgumentParser(
        prog='solve', formatter_class=HelpFormatter,
        description='Hand-eye calibration (Chou-Kamel) from a samples file: the samples CSV, '
                    'or samples saved by easy_handeye2 or moveit_calibration; prints one JSON '
                    'object.')
    parser.add_argument('samples', help='samples file: the samples CSV (README, section '
                                        "3) or another tool's samples (see --format); or an "
                                        'image dataset folder (images/, robot_poses.csv, '
                                        'camera_info.yaml, board.yaml): the board is detected '
                                        'in each image and the estimate refined on its pixels')
    add_setting_options(parser, 'solve', ESTIMATOR)
    # Unset unless given: an easy_handeye2 file may name the setup (else eye_in_hand), a
    # journal its setup and invert_sensor (else false).
    parser.set_defaults(setup=None, invert_sensor=None)
    parser.add_argument('--no-invert-sensor', action='store_true',
                        help="the sensor poses are not inverted, whatever the journal's header "
                             'says')
    parser.add_argument(
        '--format', choices=('auto',) + importers.FORMATS, default='auto',
        help='format of the samples file. auto (default): .csv = samples CSV, .samples = '
             'easy_handeye2, .json = moveit pose_samples.json, other names by content. '
             'easy_handeye2: its .samples YAML (robot, tracking transforms); moveit: '
             'moveit_calibration samples YAML (effector_wrt_world, object_wrt_sensor, 16 '
             'numbers row-major); moveit-json: [[eef_wrt_world, obj_wrt_sensor], ...] 4x4')
    add_frame_arguments(parser)
    add_report_argument(parser)
    parser.add_argument('--result-out', metavar='FILE.yaml',
                        help="also write the result YAML (as the node's ~/save and replay's "
                             '--result-out)')
    add_easy_handeye2_argument(parser)
    args = parser.parse_args(argv)
    if args.no_invert_sensor:
        if args.invert_sensor:   # (the last of the two had won)
            parser.error('--invert-sensor and --no-invert-sensor say opposite things: give one')
        args.invert_sensor = False
    asked_invert, args.invert_sensor = args.invert_sensor, bool(args.invert_sensor)
    try:
        settings_of(args, setup=args.setup or 'eye_in_hand')   # the file may name the setup
    except ConfigError as error:
        return fail(parser.prog, f'bad option: {error}', EXIT_BAD_INPUT)
    if not args.samples.strip():
        return fail(parser.prog, 'the samples path is empty: give a samples file or an image '
                                 'dataset folder', EXIT_BAD_INPUT)
    folder = Path(args.samples).is_dir()
    outputs = {'--report': args.report, '--result-out': args.result_out,
               '--easy-handeye2-out': args.easy_handeye2_out}
    problem = output_problem([('dataset' if folder else 'file', args.samples)], outputs)
    if problem:
        return fail(parser.prog, problem, EXIT_BAD_INPUT)
    if folder and _is_bag(Path(args.samples)):
        return fail(parser.prog, f'{args.samples} is a rosbag2 recording, not a samples file '
                                 'or an image dataset folder: replay reads it (python -m '
                                 f'quatcal_ros replay {args.samples} --link-topic TOPIC '
                                 '--sensor-topic TOPIC)', EXIT_BAD_INPUT)
    if folder:
        if args.invert_sensor:
            return fail(parser.prog, f'bad option: {IMAGES_NOT_INVERTED}', EXIT_BAD_INPUT)
        return _solve_images(parser.prog, args)
    try:
        imported = importers.load_samples(args.samples, args.format, args.setup, asked_invert)
    except BadInputError as error:
        return fail(parser.prog, error, EXIT_BAD_INPUT)
    args.setup = args.setup or imported.setup or 'eye_in_hand'
    args.invert_sensor = bool(imported.invert_sensor)
    try:
        frames = solve_frames(args, imported.frames)
    except BadInputError as error:
        return fail(parser.prog, f'{args.samples}: {error}', EXIT_BAD_INPUT)
    session = Session(session_config(settings_of(args)))
    copies = _copies(session.add_samples(imported.samples))
    session.estimate()   # one full solve over all of them
    warnings = [*imported.warnings, *_copies_warning(copies, imported.rows),
                *moved_marker(session)]
    frames, tree, said = _journal_tree(imported, frames)
    warnings += said
    failed = _write_files(parser.prog, args, session.result, frames, warnings, imported.frames,
                          tree=tree)
    if failed:
        return failed
    return print_result(parser.prog, session, f'{args.samples}: ', warnings, frames=frames,
                        limits=plan_limits(settings_of(args)),
                        report=args.report, tree=tree)


def _is_bag(folder):
    """Return whether `folder` holds a rosbag2 recording (its metadata, or its storage files)."""
    return ((folder / bag_folder.INDEX).is_file()
            or bool(bag_folder.storage_files(folder, bag_folder.READABLE_SUFFIXES)))


def _journal_tree(imported, frames):
    """
    Return (frames, the TF tree a journal recorded for the result's joint or None, warnings).

    The tree is the journal's static_chain, for the sensor frame it was recorded for: another
    child frame (--child-frame) has none. A child frame that is the chain's top (camera_link
    above its optical frame) is what the joint gives: the result stays the sensor frame's.
    """
    named = imported.frames.get('tracking_base_frame')
    if imported.static_chain is None or named is None:
        return frames, None, []
    sensor, root = normalize_frame(named), normalize_frame(imported.static_chain[0])
    warnings = []
    if frames[1] == root:
        warnings.append(f'--child-frame {root} is the top of the static chain above the '
                        f"sensor frame {sensor} in the journal's TF tree: the result is the "
                        f'calibrated {frames[0]} -> {sensor}, and its static_transform_publisher '
                        f'line and URDF joint are {frames[0]} -> {root} (the transform to '
                        f'{root})')
        frames = (frames[0], sensor)
    if frames[1] != sensor:
        return frames, None, warnings
    return frames, tf_joint.recorded_tree(sensor, imported.static_chain), warnings


def _solve_images(prog, args):
    """`solve DIR`: the board in each image, the pose-based estimate, then on the pixels."""
    from quatcal_ros.vision import dataset as images   # cv2 only on the image path
    from quatcal_ros.vision.image_sensor import result_on_pixels
    from quatcal_ros.vision.reprojection import refine_from_poses
    args.setup = args.setup or 'eye_in_hand'
    where = f'{args.samples}: '
    try:
        frames = solve_frames(args)
    except BadInputError as error:
        return fail(prog, error, EXIT_BAD_INPUT)
    progress = Progress(None, 'images', enabled=sys.stderr.isatty())

    def show(done, total):
        progress.total = total
        progress.update(done)
    try:
        data = images.load_image_dataset(args.samples, progress=show)
    except BadInputError as error:
        return fail(prog, error, EXIT_BAD_INPUT)
    finally:
        progress.close()
    total = len(data.samples) + len(data.refused)   # one of them per row of robot_poses.csv
    session = Session(session_config(settings_of(args), images=True))
    data.refuse_copies(_copies(session.add_samples(data.samples)))
    session.estimate()
    views = {'used': len(data.samples), 'refused': data.refused_json()}
    result = session.result and _named_by_image(session.result, data.names)
    if len(data.samples) < 3:
        refused = f'. Refused: {data.refusal_summary()}' if data.refused else ''
        return fail(prog, f'{where}{len(data.samples)} of {total} images gave a usable board '
                          f'pose; at least 3 are needed{refused}', EXIT_BAD_INPUT)
    if result is None:   # why there is none
        return print_result(prog, session, where)
    if result.unobservable:   # as the node and replay: the pixel fit has no gauge there
        warnings = [_on_poses(REDUCED_DOF_ON_POSES)]
        failed = _write_files(prog, args, result, frames, warnings)
        return failed or print_result(
            prog, session, where, warnings, frames=frames,
            result=result,
            limits=plan_limits(settings_of(args)), report=args.report,
            extra={'views': views, 'pose_based_method': result.method})
    fit = refine_from_poses(data.samples, data.corners(), data.camera, result, args.setup,
                            args.robust)
    on_pixels = _named_by_image(result_on_pixels(session.result, fit), data.names)
    # On images the usual cause: the board's or the camera's numbers, which no fit can see.
    hint = (['on camera images a failed validation most often means wrong numbers in '
             'board.yaml (square_length_m, marker_length_m: measure the printed board) or '
             'camera_info.yaml (the camera matrix; zero distortion for rectified images)']
            if 'fail' in (on_pixels.validation.get('verdict'), result.validation.get('verdict'))
            else [])
    if data.refused:   # said only in the JSON's views.refused, and on no page
        hint.append(f'{len(data.refused)} of {total} images are not used: '
                    f'{data.refusal_summary()} (the "views" key lists each)')
    if data.unlisted:   # (an image without its row was left out without a word)
        hint.append(data.unlisted_summary())
    failed = _write_files(prog, args, on_pixels, frames, hint)
    if failed:
        return failed
    return print_result(prog, session, where, hint, frames=frames, result=on_pixels,
                        limits=plan_limits(settings_of(args)), report=args.report,
                        extra={'views': views, 'pose_based_method': result.method})


REDUCED_DOF_ON_POSES = 'a robot that cannot turn the link freely is solved on the poses'


def _named_by_image(result, names):
    """
    Return `result` with every entry that names a sample naming its image too (solve DIR).

    A rejected sample's reason adds the other usual cause in a folder: the wrong row. The fit
    on the pixels (reprojection) names its worst view's image.
    """
    def named(entries):
        return [{**entry, 'image': names[entry['sample']]} if 'sample' in entry else entry
                for entry in entries]
    validation = {key: named(value) if key in ('samples', 'worst') else value
                  for key, value in result.validation.items()}
    rejected = [{**entry, 'reason': f'{entry["reason"]}; or the image is paired with the '
                                    'wrong robot pose: check its row in robot_poses.csv'}
                if 'image' in entry else entry for entry in named(result.rejected)]
    reprojection = result.reprojection and {
        **result.reprojection,
        'worst_view_image': names[result.reprojection['worst_view_sample']]}
    return replace(result, rejected=rejected, noisy=named(result.noisy), validation=validation,
                   reprojection=reprojection)


def _on_poses(why):
    """Return the warning of an image input whose estimate stays on the board poses."""
    return f'the estimate is on the board poses, not on the pixels: {why}'


def _write_files(prog, args, result, frames, warnings=(), named=None, source=None,
                 tree=None, causes=()):
    """
    Write --result-out and --easy-handeye2-out, those given, when there is a result.

    Return fail's status, or None. warnings: those the printed result adds (published).
    named: the frames the samples file named, by easy_handeye2 parameter name (the base or
    effector frame and the marker frame that the result's frames do not give).
    source: the result file's "source" (default: `solve`'s samples); tree: the TF tree the
    joint joins (tf_joint.joint: a replay over TF, a journal's static_chain), or None;
    causes: as validation.published takes them.
    """
    easy_handeye2_out = args.easy_handeye2_out
    if result is None or not (args.result_out or easy_handeye2_out):
        return None
    named = named or {}
    keep = ('robot_base_frame' if args.setup == 'eye_in_hand' else 'robot_effector_frame',
            'tracking_marker_frame')
    result, mount = prepared(result, frames, warnings, tree, causes)
    saved = save_result(result, frames, args.setup,
                        result_file=args.result_out, easy_handeye2_file=easy_handeye2_out,
                        easy_handeye2_frames={key: named.get(key, '') for key in keep},
                        extra={'source': source or {'samples': str(absolute(args.samples))}},
                        joint=mount)
    for _, target, error in saved.failed:
        return fail(prog, f'{target}: cannot write: {error}', EXIT_BAD_INPUT)
    return None


def _copies(events):
    """
    Return {position: position of the sample it repeats} of a fresh session's 'repeated' refusals.

    events: those of Session.add_samples of one list; positions count from 0 in that list.
    """
    refused = [event for event in events if isinstance(event, Rejected)]
    dropped = {event.given for event in refused}
    stored = [k for k in range(max(dropped, default=-1) + 1) if k not in dropped]
    return {event.given: stored[event.repeats] for event in refused if event.code == 'repeated'}


def _copies_warning(copies, rows=None):
    """
    Return the warning (a list of one, or none) that `copies` were each counted once.

    rows: the file row of each sample (a CSV's), which name them; else their numbers from 0.
    """
    if not copies:
        return []
    name = (lambda k: rows[k]) if rows else (lambda k: k)
    pairs = ', '.join(f'{name(copy)} = {name(original)}'
                      for copy, original in list(copies.items())[:10])
    more = ', ...' if len(copies) > 10 else ''
    what = ('row = the row it repeats, rows of the file as its errors count them' if rows else
            'sample = the one it repeats, numbered from 0 in the file')
    return [f'{len(copies)} sample(s) repeat earlier ones exactly ({what}: {pairs}{more}): a '
            'copied row is not a new measurement, so each was counted once; the sample '
            'numbers elsewhere in this output count the samples kept, in file order']


def add_easy_handeye2_argument(parser):
    """--easy-handeye2-out FILE of `solve` and `replay`."""
    parser.add_argument('--easy-handeye2-out', metavar='FILE',
                        help='also write the result in the easy_handeye2 calibration layout '
                             '(e.g. ~/.ros2/easy_handeye2/calibrations/NAME.calib)')


def add_report_argument(parser):
    """--report FILE.html of `solve` and `replay`."""
    parser.add_argument('--report', metavar='FILE.html',
                        help='also write a report page: the answer, the validation, each '
                             "sample's prediction error, the estimate as samples were added, "
                             'the coverage of rotation axes, the mount (one self-contained '
                             'HTML file with SVG figures; needs matplotlib)')


def write_report_file(prog, path, result, session, frames, title='', time_offset=None):
    """Write the --report page; return None, or the exit status after saying why not."""
    try:
        from quatcal_ros.report.page import write_report   # matplotlib only for a report
    except ImportError as error:
        return fail(prog, f'--report needs matplotlib ({error}): pip install matplotlib, or '
                          'apt install python3-matplotlib', EXIT_BAD_INPUT)
    try:
        write_report(path, result, session.samples, session.config.calibration, frames,
                     title, time_offset)
    except OSError as error:
        return fail(prog, f'{path}: cannot write the report: {error}', EXIT_BAD_INPUT)
    return None


def add_frame_arguments(parser):
    """--parent-frame and --child-frame of `solve`: the frames of the printed outputs."""
    parser.add_argument('--parent-frame',
                        help="the result's parent frame: the link (eye_in_hand, default "
                             'tool0) or the robot base (eye_to_hand, default base_link), or '
                             'as an easy_handeye2 file names it')
    parser.add_argument('--child-frame',
                        help='the sensor frame (default camera, or as an easy_handeye2 file '
                             'names it)')


def solve_frames(args, named=None):
    """
    Return (parent, child) frames of the outputs: the options, else the file's, else defaults.

    named: frame names from the samples file, by easy_handeye2 parameter name.
    :raises BadInputError: when they are one frame (frames_problem).
    """
    named = named or {}
    named_parent = named.get('robot_effector_frame' if args.setup == 'eye_in_hand'
                             else 'robot_base_frame')
    frames = exports.choose_frames(args.setup, (args.parent_frame, args.child_frame),
                                   (named_parent, named.get('tracking_base_frame')))
    problem = frames_problem(frames)
    if problem:
        raise BadInputError(problem)
    return tuple(normalize_frame(frame) for frame in frames)


def frames_problem(frames):
    """
    Say why the result's (parent, child) `frames` cannot be used, or ''.

    One frame twice, or one that TF cannot take (tf_tree.frame_problem: a hand-edited samples
    file gave ' ' and a name across two lines).
    """
    for frame, option in zip(frames, ('--parent-frame', '--child-frame')):
        problem = frame_problem(frame)
        if problem:
            return f'{problem}: give the frame as {option}'
    parent, child = (normalize_frame(frame) for frame in frames)
    if parent != child:
        return ''
    return (f'the result would be a transform from frame {child!r} to itself (its '
            'static_transform_publisher line, URDF joint and files): give the link frame '
            '(eye_in_hand) or the robot base frame (eye_to_hand) as --parent-frame and the '
            'sensor frame as --child-frame')


def print_result(prog, session, where='', warnings=(), frames=None, extra=None, result=None,
                 limits=PlanLimits(), report=None, tree=None, causes=()):
    """
    Print the session's result as JSON (exit 0) or why there is none (exit 2 or 3).

    warnings: sentences added to the result's own "warnings" (what the input lacked).
    frames: (parent, child) of the "static_transform_publisher" line; default
    exports.default_frames of the result's setup. extra: more keys for the JSON object.
    result: the CalibrationResult to print instead of the session's (`solve DIR`: the same
    with the estimate on the pixels at the top level). limits: the next-pose planner's.
    report: the --report path, or None; the page's title is `where` without its colon.
    tree: the TF tree of the input (replay: empty without TF input), or None: the command and
    the joint are given where the tree can take them (tf_joint.joint). causes: the input's
    problems that explain the estimate's warnings (validation.published), said first on
    stderr too.
    """
    if len(session.samples) < 3 or session.result is None:
        for warning in warnings:   # what the input lacked may be why (a journal's torn tail)
            warn(prog, f'{where}{warning}')
    if len(session.samples) < 3:
        copies = session.counters['repeated_samples']
        more = f' ({copies} more repeat earlier ones exactly)' if copies else ''
        return fail(prog, f'{where}{len(session.samples)} sample(s){more}; at least 3 are '
                          'needed', EXIT_BAD_INPUT)
    if session.result is None:
        return fail(prog, f'{where}the rotation cannot be determined: {session.last_error}',
                    EXIT_UNDETERMINED)
    result = result or session.result
    parent, child = frames or exports.default_frames(result.setup)
    result, mount = prepared(result, (parent, child), warnings, tree, causes)
    for cause in causes:   # (before the advice they make wrong: 'set setup to ...')
        warn(prog, f'{where}{cause}')
    if not result.usable:   # a script that reads only the exit status hears it here
        said = next(text for text in result.warnings if DO_NOT_USE in text)
        warn(prog, f'{where}the estimate says not to use it ("usable": false): {said}')
    failed = failure_warning(result.validation)
    if failed:   # (as in the warnings; only the JSON said it)
        warn(prog, f'{where}{failed}')
    document = result.to_json_dict()
    document['parent_frame'], document['child_frame'] = parent, child   # (the calibrated)
    document['static_transform_publisher'] = exports.static_transform_publisher_command(
        mount.result, mount.parent, mount.child)
    document.update(exports.description_joints(mount.result, mount.parent, mount.child,
                                               mount.note))
    options = session.config.calibration
    planned = plan_next_pose(session.samples, result, options.setup, options.invert_sensor,
                             limits)
    document['next_pose'] = planned.to_json_dict() if planned is not None else None
    document.update(extra or {})
    if report:
        status = write_report_file(prog, report, result, session, (parent, child),
                                   where.rstrip(': '), document.get('time_offset'))
        if status is not None:
            return status
    print(json.dumps(document, indent=2))
    return 0


def moved_marker(session):
    """
    Return the live node's moved-marker warning over all of the session's samples, or [].

    A marker or sensor bumped halfway through leaves two mountings in one file: the estimate
    lies between them, its uncertainty knows nothing of it, and only a failed validation
    hinted at it.
    """
    if session.result is None:
        return []
    options = session.config.calibration
    return [text for _, text in MoveWatch(offline=True).check(
        session.samples, session.result.quaternion, options.setup, options.invert_sensor)]


def prepared(result, frames, warnings=(), tree=None, causes=()):
    """
    Return (the CalibrationResult as printed and written, its tf_joint.Joint).

    `warnings` and `causes` added (published), and where the joint would break the TF
    `tree`, that too: the JSON and the result file say the same.
    """
    parent, child = frames
    mount = tf_joint.joint(result, frames, tree)
    if mount.breaks:   # (the command and the joint say it too)
        warnings = [*warnings, f'TF: the static_transform_publisher line and the urdf joint '
                               f'are {parent} -> {child} as calibrated, and {mount.note}']
    return published(result, warnings, causes), mount


def warn(prog, message):
    """Print `prog: warning: message` on stderr."""
    print(f'{prog}: warning: {message}', file=sys.stderr)


def fail(prog, message, status):
    """Print `prog: error: message` on stderr and return `status`."""
    print(f'{prog}: error: {message}', file=sys.stderr)
    return status


# --- replay ----------------------------------------------------------------------------------

def _seconds(ns):
    return ns / NS_PER_S


def add_capture_arguments(parser):
    """Options of how samples are taken from the paired streams (the node's parameters)."""
    group = parser.add_argument_group('capture, pairing and message checks')
    add_setting_options(group, 'replay', CAPTURE)
    group.add_argument('--no-fallback', action='store_true',
                       help='auto capture only, even when the bag has no still sample')
    add_setting_options(group, 'replay', ('sensor_time_offset_s',))
    group.add_argument('--estimate-time-offset', action='store_true',
                       help='estimate the sensor time offset from the recording (angular '
                            'speed cross-correlation refined by the residual), apply it and '
                            'report it with the residual with and without it; the offsets '
                            'searched lie within 0.5 s of the sensor time offset given '
                            '(default 0)')


CAPTURE = ('capture_mode', 'still_window_s', 'still_rotation_deg', 'still_translation_m',
           'sensor_still_rotation_deg', 'sensor_still_translation_m', 'min_still_pairs',
           'continuous_step_deg', 'max_gap_s', 'pairing_tolerance_s', 'link_frame_id',
           'sensor_frame_id', 'max_position_m')


def absolute_topic(name):
    """Return a topic name as a bag holds it: resolved in the root namespace (a/b -> /a/b)."""
    return name if name.startswith('/') else '/' + name


def replay_parser():
    """Return the argument parser of `replay`."""
    parser = argparse.ArgumentParser(
        prog='replay', formatter_class=HelpFormatter,
        description='Hand-eye calibration (Chou-Kamel) from a rosbag2 recording (sqlite3 or '
                    "mcap), through the live node's session; prints one JSON object.")
    parser.add_argument('bag', metavar='BAG_DIR', help='rosbag2 directory (or .db3/.mcap file)')
    inputs = parser.add_argument_group(
        'inputs', 'link poses T_base_link and sensor poses T_sensor_obj, each from a topic '
                  '(geometry_msgs PoseStamped, TransformStamped, PoseWithCovarianceStamped, '
                  'nav_msgs/Odometry) or from the TF tree')
    link = inputs.add_mutually_exclusive_group(required=True)
    link.add_argument('--link-topic', metavar='T', type=absolute_topic,
                      help='topic of the link poses')
    link.add_argument('--link-frames', nargs=2, metavar=('BASE', 'LINK'),
                      help='link pose T_BASE_LINK from the TF topics')
    sensor = inputs.add_mutually_exclusive_group(required=True)
    sensor.add_argument('--sensor-topic', metavar='T', type=absolute_topic,
                        help='topic of the sensor poses')
    sensor.add_argument('--sensor-frames', nargs=2, metavar=('SENSOR', 'OBJECT'),
                        help='sensor pose T_SENSOR_OBJECT from the TF topics')
    sensor.add_argument('--image-topic', metavar='T', type=absolute_topic,
                        help='camera images (sensor_msgs Image or CompressedImage): the board '
                             'of --board-file is found in each, and the estimate is refined '
                             'on the corners of the samples')
    inputs.add_argument('--camera-info-topic', metavar='T', type=absolute_topic,
                        help='CameraInfo of --image-topic (default: camera_info beside it, '
                             'e.g. /camera/color/camera_info for /camera/color/image_raw)')
    inputs.add_argument('--tf-topics', nargs='+', metavar='T', type=absolute_topic,
                        default=['/tf', '/tf_static'],
                        help='TFMessage topics read with --*-frames; names ending in '
                             'tf_static hold static transforms (default: /tf /tf_static)')
    add_setting_options(inputs, 'replay', ('board_file',))
    add_setting_options(parser, 'replay', ESTIMATOR)
    add_capture_arguments(parser)
    outputs = parser.add_argument_group('outputs')
    outputs.add_argument('--samples-out', metavar='FILE.csv',
                         help='write the captured samples (samples CSV, input of `solve`)')
    outputs.add_argument('--journal-out', metavar='FILE.csv',
                         help="write the captured samples as the live node's samples journal "
                              '(samples_file; resume:=true continues it); an existing file is '
                              'moved aside, never overwritten')
    outputs.add_argument('--result-out', metavar='FILE.yaml',
                         help="write the result YAML (as the node's ~/save)")
    add_easy_handeye2_argument(outputs)
    outputs.add_argument('--parent-frame', help='parent frame in --result-out (default: the '
                                                'link frame, or base frame for eye_to_hand, '
                                                'as the messages name it)')
    outputs.add_argument('--child-frame', help='child (sensor) frame in --result-out '
                                               '(default: as the messages name it)')
    add_report_argument(outputs)
    outputs.add_argument('--partial', action='store_true',
                         help='use what a damaged recording still gives (the result says how '
                              'many indexed messages could not be read); without it such a '
                              'recording exits 2')
    outputs.add_argument('--quiet', action='store_true',
                         help='no progress bar and no summary on stderr')
    return parser


def replay_main(argv=None):
    """`replay BAG_DIR ...`: estimate the mounting from a rosbag2 recording, print JSON."""
    parser = replay_parser()
    args = parser.parse_args(argv)
    prog = parser.prog
    try:
        chosen = settings_of(args)
    except ConfigError as error:
        return fail(prog, f'bad option: {error}', EXIT_BAD_INPUT)
    config = session_config(chosen, images=args.image_topic is not None)
    if args.parent_frame and args.child_frame:   # (before reading the bag)
        one_frame = frames_problem((args.parent_frame, args.child_frame))
        if one_frame:
            return fail(prog, one_frame, EXIT_BAD_INPUT)
    problem = output_problem([('bag', args.bag), ('file', args.board_file)], {
        '--samples-out': args.samples_out, '--journal-out': args.journal_out,
        '--result-out': args.result_out, '--report': args.report,
        '--easy-handeye2-out': args.easy_handeye2_out})
    if problem:
        return fail(prog, problem, EXIT_BAD_INPUT)
    try:
        from quatcal_ros.ros import bag   # rosbags is needed by the replay only
    except ImportError as error:
        return fail(prog, f'the replay needs the rosbags package ({error}): pip install '
                          "'rosbags>=0.10,<0.12'", EXIT_BAD_INPUT)
    try:
        link = bag.PoseInput(topic=args.link_topic, frames=args.link_frames)
        sensor, images = _sensor_input(bag, args, config)
    except BadInputError as error:
        return fail(prog, error, EXIT_BAD_INPUT)
    start = time.monotonic()
    try:
        with bag.Bag(args.bag) as recording:
            replay = bag.Replay(recording, link, sensor, tuple(args.tf_topics),
                                checks=check_config(chosen), images=images)
            time_offset = None
            if args.estimate_time_offset:
                session, report, notes, time_offset = _replay_with_time_offset(
                    replay, config, args)
            else:
                session, report, notes = _replay(replay, config, args)
    except bag.BagError as error:
        partial = ('; pass --partial to use what could be read'
                   if isinstance(error, bag.DamagedStorage) else '')
        return fail(prog, f'{error}{partial}', EXIT_BAD_INPUT)
    except KeyboardInterrupt:
        return fail(prog, 'interrupted', EXIT_INTERRUPTED)
    if not args.quiet:
        _summary(prog, report, session, time.monotonic() - start)
    if report.unread and not args.partial:
        return fail(prog, f'{args.bag}: the recording is damaged: read only '
                          f'{report.unread_text()}; pass --partial to use what could be read',
                    EXIT_BAD_INPUT)
    where = f'{args.bag}: '
    one_frame = frames_problem(_replay_frames(args, report))   # one option and the messages'
    if one_frame:
        return fail(prog, f'{where}{one_frame} (nothing written)', EXIT_BAD_INPUT)
    if len(session.samples) < 3:   # no output written: a file from an earlier run stays
        outputs = (('--samples-out', args.samples_out), ('--journal-out', args.journal_out))
        unwritten = [option for option, path in outputs if path]
        logged = bag.clock_offset_ns(replay, report)
        return fail(prog, where + _too_few_samples(session, report, link, sensor, logged)
                    + (f' ({" and ".join(unwritten)} not written)' if unwritten else ''),
                    EXIT_BAD_INPUT)
    if args.samples_out:
        try:
            atomic_write_text(args.samples_out, format_samples(session.samples))
        except OSError as error:
            return fail(prog, f'{args.samples_out}: cannot write: {error}', EXIT_BAD_INPUT)
    if args.journal_out:
        status = _write_journal(prog, args, session, report)
        if status:
            return status
    # The session estimates when asked, so only now: one full solve over all the samples,
    # exactly what `solve` computes from the --samples-out file.
    session.estimate()
    warnings = (notes + report.warnings()
                + bag.frame_warnings(report, args.setup, args.invert_sensor))
    # TF frames given swapped explain the convention advice and the failed validation.
    causes = bag.swapped_frames(report, session.result)
    if not args.estimate_time_offset:   # (the search starts from what the log times say)
        warnings += _logged_clocks(bag.clock_offset_ns(replay, report),
                                   config.sensor_offset_ns)
    warnings += moved_marker(session)
    extra = {'time_offset': time_offset} if time_offset else {}
    on_pixels = None
    if images is not None:
        extra['views'] = {'used': len(images.corners), 'counts': dict(images.counts)}
        on_pixels = images.on_pixels(session.samples, session.result, args.setup, args.robust)
        if on_pixels is None and session.result is not None:
            warnings.append(_on_poses(
                REDUCED_DOF_ON_POSES if session.result.unobservable else
                f'{len(images.corners)} samples kept corners (3 are needed; the time-offset '
                'search keeps none)'))
    if on_pixels is not None:
        extra['pose_based_method'] = session.result.method
    if not args.estimate_time_offset:   # (the answer's uncertainty: on the pixels, if so)
        warnings += _moving_samples(session, on_pixels and on_pixels[0])
    if session.result is not None and (args.result_out or args.easy_handeye2_out):
        status = _write_result(prog, args, on_pixels[0] if on_pixels else session.result,
                               session, warnings, report, link, sensor, causes)
        if status:
            return status
    return print_result(prog, session, where, warnings, frames=_replay_frames(args, report),
                        extra=extra, result=on_pixels and on_pixels[0],
                        limits=plan_limits(settings_of(args)), report=args.report,
                        tree=report.tree, causes=causes)


def _sensor_input(bag, args, config):
    """Return (bag.PoseInput of the sensor, vision ImageSensor or None) of the options."""
    if args.image_topic is None:
        for option, given in (('--camera-info-topic', args.camera_info_topic),
                              ('--board-file', args.board_file)):
            if given:   # (it was once ignored: the answer came from --sensor-topic)
                raise BadInputError(f'{option} goes with --image-topic')
        return bag.PoseInput(topic=args.sensor_topic, frames=args.sensor_frames), None
    if not args.board_file:
        raise BadInputError('--image-topic needs --board-file: the board.yaml of the target')
    if args.invert_sensor:
        raise BadInputError(IMAGES_NOT_INVERTED)
    from quatcal_ros.vision.board import read_board   # cv2 only on the image path
    from quatcal_ros.vision.image_sensor import ImageSensor
    image = next((args.image_topic[:-len(suffix)] for suffix in TRANSPORT_SUFFIXES
                  if args.image_topic.endswith(suffix)), args.image_topic)
    beside = image.rsplit('/', 1)[0] + '/' if '/' in image else ''
    info = args.camera_info_topic or beside + 'camera_info'
    return (bag.PoseInput(topic=args.image_topic, camera_info=info),
            ImageSensor(read_board(args.board_file), session_config=config))


# image_transport names a transport's topic after the image topic: IMAGE/compressed, ...
TRANSPORT_SUFFIXES = ('/compressed', '/compressedDepth', '/theora', '/zstd', '/ffmpeg')


class _StreamRecorder:
    """Stand-in for a Session that keeps both pose streams (for the time-offset search)."""

    held = frozenset()   # every pose is kept: none waits undecided

    def __init__(self):
        self.link, self.sensor = RecordedStream(), RecordedStream()
        self.counters = {}

    def end_streams(self):
        return []

    def add_link_pose(self, stamp_ns, pose):
        self.link.append(stamp_ns, pose)
        return []

    def add_sensor_pose(self, stamp_ns, pose):
        self.sensor.append(stamp_ns, pose)
        return []

    def add_poses(self, stream, stamps_ns, positions, quaternions_wxyz):
        getattr(self, stream).extend(stamps_ns, positions, quaternions_wxyz)
        return []


# A clock offset the bag's log times show beyond this centres the time-offset search on it.
LOGGED_OFFSET_NS = 250_000_000


def _logged_clocks(logged_ns, given_ns):
    """
    Return [the warning on clocks the bag's log times show offset beyond the one given], or [].

    As the node's (stream/arrival_lag.py): beyond APART_NS, poses pair with the wrong partners
    (the link buffer holds 2 s) and the answer is wrong with no other sign than its residual.
    """
    if logged_ns is None or abs(logged_ns - given_ns) <= APART_NS:
        return []
    given = f' (with --sensor-time-offset {given_ns / NS_PER_S:g})' if given_ns else ''
    late = 'sensor' if logged_ns > given_ns else 'link'   # the stream that reached it later
    return [f"{stamps_apart(logged_ns - given_ns)}{given} against the bag's log times: the "
            'clocks are offset, and poses may have been paired with the wrong partners; '
            f'{_logged_fix(logged_ns)} (or the {late} poses took that long to reach the '
            'recorder)']


# The stamp offset whose effect on samples taken in motion is weighed (_moving_samples).
OFFSET_WEIGHED_NS = 10_000_000


def _moving_samples(session, published=None):
    """
    Return [the hint that samples taken in motion need the time offset], or [].

    With continuous capture and no sensor time offset given: stamps of two devices are
    rarely the same moment (a camera stamps at the end of its exposure, a driver when it
    sends), and tens of ms matter in motion (the ETH arm recording's 20 ms moved its answer
    by 1.3 times its uncertainty). How far 10 ms moves the samples lets the user judge.
    published: the answer printed when it is not the session's (on the pixels): its
    uncertainty is the one to weigh the shift against.
    """
    result = session.result
    if (result is None or session.config.capture.mode != 'continuous'
            or session.config.sensor_offset_ns):
        return []
    speed = link_speed_deg_s(session.samples)
    if speed is None:
        return []
    shift = speed * OFFSET_WEIGHED_NS / NS_PER_S
    return [f'the samples were taken while the link turned (median {speed:.1f} deg/s between '
            f'them): each {OFFSET_WEIGHED_NS / 1e6:.0f} ms by which the sensor stamps are off '
            f'moves them by about {shift:.2g} deg (the uncertainty: '
            f'{(published or result).uncertainty_deg:.2g} deg); --estimate-time-offset '
            'measures the offset (or give it, --sensor-time-offset)']


def _logged_fix(logged_ns):
    """Say what corrects the clock offset logged_ns the bag's log times show."""
    return (f'--sensor-time-offset {logged_ns / NS_PER_S:.2f} corrects it, and '
            '--estimate-time-offset measures it, searching around that')


def _replay_with_time_offset(replay, config, args):
    """Read both streams, find the sensor time offset, replay with it applied."""
    from quatcal_ros.ros import bag   # rosbags is needed by the replay only
    from quatcal_ros.report.page import offset_sentence   # (matplotlib only when drawn)
    recorder = _StreamRecorder()
    report = replay.run(recorder, partial=args.partial)
    # Candidate offsets are scored by the closed-form estimate's residual: many solves, each
    # far cheaper than the refinement's.
    scoring = replace(config.calibration, method='closed-form')
    notes = []
    logged = bag.clock_offset_ns(replay, report)
    if not config.sensor_offset_ns and logged is not None and abs(logged) > LOGGED_OFFSET_NS:
        # Clocks this far apart would put the true offset at the edge of the search or
        # beyond: search around what the bag's log times say instead (to 10 ms).
        config = replace(config, sensor_offset_ns=int(round(logged, -7)))
        notes.append(f"{stamps_apart(logged)} against the bag's log times: the time offset "
                     f'was searched around {config.sensor_offset_ns / NS_PER_S:+.2f} s')
    try:
        found, session = find_time_offset(recorder.link, recorder.sensor,
                                          config, residual_options=scoring)
        continuous = _fallback(config, session, args)
        if continuous is not None:   # as _replay does, on the streams already read
            notes.append(_fallback_note(config.capture, session))
            found, session = find_time_offset(recorder.link, recorder.sensor,
                                              continuous, residual_options=scoring)
    except ValueError as error:
        raise bag.BagError(f'{args.bag}: cannot estimate the time offset: {error}') from None
    report.counters = session.counters
    offset = found.to_json_dict()
    return session, report, [f'time offset: {offset_sentence(offset)}', *notes], offset


def _replay(replay, config, args):
    """Run the replay; in auto mode without any still sample, again in continuous mode."""
    session, report = _run(replay, config, args, 'replay')
    notes = []
    continuous = _fallback(config, session, args)
    if continuous is not None:
        notes.append(_fallback_note(config.capture, session))
        session, report = _run(replay, continuous, args, 'replay (continuous)')
    return session, report, notes


def _fallback(config, session, args):
    """Return the continuous-capture config when auto capture found no still, else None."""
    capture = config.capture
    if (capture.mode == 'auto' and not session.samples and session.counters['pairs']
            and not args.no_fallback):
        return replace(config, capture=replace(capture, mode='continuous'))
    return None


def _fallback_note(capture, session):
    return (f'no still samples in auto mode (the poses never stayed within the still bands '
            f'for {_seconds(capture.window_ns):g} s{_unsteady_sensor(capture, session)}): '
            f'samples taken in continuous mode instead, one per '
            f'{capture.continuous_step_deg:g} deg of link rotation; pass --capture continuous '
            'to skip the auto pass')


def _unsteady_sensor(capture, session):
    """Say so when the link stood still but the sensor pose did not, else ''."""
    return unsteady_sensor_note(session.counters['unsteady_sensor'], capture,
                                ('--sensor-still-rotation-deg', '--sensor-still-translation-m'),
                                session.sensor_scatter)


def _run(replay, config, args, label):
    images = replay.images
    if images is not None:
        images.configure(config)
    session = Session(config, on_sample=None if images is None else images.keep)
    progress = Progress(replay.total, label, enabled=not args.quiet)

    def extra():
        counters = session.counters
        return f'samples {counters["samples"]}, motions {counters["motions"]}'

    on_progress = (lambda done: progress.update(done, extra)) if progress.enabled else None
    try:
        report = replay.run(session, on_progress, partial=args.partial)
    finally:
        progress.close(None, extra)
    return session, report


def _summary(prog, report, session, seconds):
    counters = session.counters
    jumps = counters['sensor_jumps']
    jumps = (f'; {jumps} sensor poses left out of still samples: they jumped over '
             f'{JUMP_BANDS:g}x the sensor bands' if jumps else '')
    print(f'{prog}: {report.messages} messages in {seconds:.1f} s: '
          f'{counters["link_messages"]} link and {counters["sensor_messages"]} sensor poses, '
          f'{counters["pairs"]} pairs, {counters["samples"]} samples '
          f'({session.config.capture.mode} capture{jumps})', file=sys.stderr)


def _missing_static_hint(report, frames):
    """Suggest /tf_static when a frame of `frames` (a FramePoses) is in no transform, or ''."""
    if frames.dropped['frames not connected'] == 0:
        return ''
    missing = [f for f in (frames.target, frames.source) if f not in report.tf_frames]
    if not missing:
        return ''
    statics = report.static_tf_topics
    if not statics and report.static_tf_unread:
        return (f'. The bag has {" and ".join(report.static_tf_unread)}, but --tf-topics did '
                'not ask for it: fixed frames (those of robot_state_publisher, a camera '
                "driver's optical frame) are published there; add it to --tf-topics")
    if not statics:
        return ('. The bag has no /tf_static: fixed frames (those of robot_state_publisher, '
                "a camera driver's optical frame) are published there; record it too (ros2 bag "
                'record /tf /tf_static ...) or give frames the /tf messages connect')
    return (f'. No transform on {" or ".join(statics)} names {" or ".join(missing)} '
            'either: check the frame name (the frames above are those the bag holds), or '
            'whether what publishes it ran while the bag was recorded')


def _too_few_samples(session, report, link, sensor, logged_ns=None):
    """
    Say why fewer than 3 samples came out of the bag, and what to try.

    logged_ns: as _few_samples takes it.

    With what the replay could not use (report.warnings: skipped messages and transforms,
    time jumps): the cause is often there (every transform refused as a loop, every sensor
    stamp the same), not in the clocks or the stops.
    """
    counters = report.counters
    for stream, source in (('link', link), ('sensor', sensor)):
        if counters[f'{stream}_messages']:
            continue
        why = f'no {stream} poses from {source}'
        frames = report.tf_dropped.get(stream)
        if frames is not None and frames.last_dropped:
            why += f' ({frames.last_dropped})'
        elif frames is not None and frames.static_chain:
            why += (f' (every transform between {frames.target} and {frames.source} is static: '
                    'no pose moves; are these the frames of the moving link and the sensor?)')
        if frames is not None:
            why += f'; frames in the TF topics: {", ".join(report.tf_frames) or "none"}'
            why += _missing_static_hint(report, frames)
        return why + _not_used(report, said=(stream,))
    return _few_samples(session, report, logged_ns) + _not_used(report)


def _not_used(report, said=()):
    """Return '; not used: ...' of the replay's warnings, or ''."""
    notes = report.warnings(said)
    return '; not used: ' + '; '.join(notes) if notes else ''


def _few_samples(session, report, logged_ns=None):
    """
    Say why the poses that came gave fewer than 3 samples.

    logged_ns: the sensor clock's offset the bag's log times show (bag.clock_offset_ns), or
    None: what the correction suggested for stamps that never pair is taken from.
    """
    counters = report.counters
    if not counters['pairs']:
        (l0, l1), (s0, s1) = report.stamps['link'], report.stamps['sensor']
        said = (f'no link pose could be paired with a sensor pose: link stamps '
                f'{l0 / NS_PER_S:.3f} to {l1 / NS_PER_S:.3f} s, sensor stamps '
                f'{s0 / NS_PER_S:.3f} to {s1 / NS_PER_S:.3f} s')
        apart = min(l1, s1) <= max(l0, s0)
        given = session.config.sensor_offset_ns
        if (logged_ns is not None and abs(logged_ns) > LOGGED_OFFSET_NS
                and abs(logged_ns - given) > LOGGED_OFFSET_NS):   # (not the offset given)
            # The recorder's clock saw both streams: their stamps' offset from it is the
            # clocks' offset, whenever each stream started.
            return (said + f' ({"they do not overlap" if apart else "they overlap"}, and '
                    f"against the bag's log times {stamps_apart(logged_ns)}: the clocks are "
                    f'offset; {_logged_fix(logged_ns)})')
        if apart:
            return said + ' (they do not overlap: are both stamped on the same clock?)'
        # They overlap, yet no two came close enough as the bag was read: a clock offset
        # beyond what the pairing keeps (PairingConfig.window_ns).
        offset = l0 - s0   # what the first stamps say the sensor clock is off
        return (said + f' (they overlap, but {stamps_apart(offset, 1)} throughout, beyond the '
                'pairing window: the clocks are offset; if that is the offset, '
                f'--sensor-time-offset {offset / NS_PER_S:.1f} corrects it, and with '
                '--estimate-time-offset too the search measures it within 0.5 s of that)')
    count, pairs = len(session.samples), counters['pairs']
    capture = session.config.capture
    if capture.mode == 'continuous':
        return (f'{count} sample(s) from {pairs} paired poses; at least 3 are needed: the '
                f'link must turn by {capture.continuous_step_deg:g} deg between samples '
                '(--continuous-step-deg)')
    return (f'{count} still sample(s) from {pairs} paired poses; at least 3 are needed: '
            f'the robot must stop for {_seconds(capture.window_ns):g} s (link within '
            f'{capture.rotation_band_deg:g} deg and {capture.translation_band_m:g} m) after '
            f'each motion of {capture.min_departure_deg:g} deg or more'
            f'{_unsteady_sensor(capture, session)}; for a recording without stops use '
            '--capture continuous')


def _replay_frames(args, report):
    """Return (parent, child) of the outputs: the options, the messages' frames, defaults."""
    from quatcal_ros.ros.bag import result_frames
    return tuple(normalize_frame(frame) for frame in exports.choose_frames(
        args.setup, (args.parent_frame, args.child_frame),
        result_frames(report, args.setup, args.invert_sensor)))


def _write_journal(prog, args, session, report):
    """Write the samples as a samples journal (the node's samples_file, resume:=true reads it)."""
    parent, child = _replay_frames(args, report)
    try:
        header = JournalHeader(args.setup, parent, child, args.invert_sensor,
                               tf_joint.static_chain(parent, child, report.tree),
                               (session.config.sensor_offset_ns / NS_PER_S,))
        record = SamplesJournal(args.journal_out, header, resume=False, resumable=False)
    except (JournalRefused, OSError) as error:
        return fail(prog, f'{args.journal_out}: cannot write: {error}', EXIT_BAD_INPUT)
    messages = record.append(session.samples) + record.sync()
    record.close()
    for level, text in record.report.messages + messages:
        # A foreign file at the path is an error for the node; here it was moved aside and
        # the journal written: nothing lost, a warning.
        level = 'warning' if level == 'error' and not messages else level
        if level != 'info' or not args.quiet:
            print(f'{prog}: {level}: {text}', file=sys.stderr)
    return EXIT_BAD_INPUT if messages else 0


def _write_result(prog, args, result, session, warnings, report, link, sensor, causes=()):
    from quatcal_ros.ros.bag import result_frames, seen_frames
    seen = result_frames(report, args.setup, args.invert_sensor)
    frames = _replay_frames(args, report)
    for role, given, chosen in zip(('parent', 'child'),
                                   (args.parent_frame or seen[0], args.child_frame or seen[1]),
                                   frames):
        if not given and not args.quiet:
            print(f'{prog}: note: the messages name no {role} frame for the result (a '
                  'PoseStamped names only the frame it is in, not a child frame): '
                  f'{chosen!r} written to {args.result_out or args.easy_handeye2_out}; '
                  f'--{role}-frame sets it', file=sys.stderr)
    source = {'bag': str(absolute(args.bag)), 'link': str(link), 'sensor': str(sensor),
              'capture': session.config.capture.mode}
    return _write_files(prog, args, result, frames, warnings,
                        seen_frames(report, args.invert_sensor), source=source,
                        tree=report.tree, causes=causes)


if __name__ == '__main__':
    sys.exit(solve_main())
