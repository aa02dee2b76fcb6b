"""
The live calibrator node: pose topics in, hand-eye estimate out (DESIGN.md contract 4).

A thin shell: the session (stream/session.py) does the work, and this node wires it to ROS.
- takes its poses through inputs.NodeInputs: the topics `link_pose` and `sensor_pose`, or
  /tf and /tf_static when the four TF frames are set, or (sensor_input:=image) camera images
  on `image` with `camera_info`, whose board poses are the sensor poses and whose corners each
  sample keeps (image_samples.py: the published estimate is refined on them); each message is
  checked, converted and counted with the checks the replay runs, bad ones are logged
  throttled;
- publishes `~/rotation` (QuaternionStamped, latched, frame_id = link_frame) and
  `~/transform` (TransformStamped link_frame -> sensor_frame, latched; with TF input the TF
  frames when those two are left at their defaults: Settings.result_frames) on each estimate,
  and `~/next_pose` (PoseStamped, latched, in the robot base frame: core/planner.py's link
  pose that most shrinks the uncertainty), and `~/markers` (MarkerArray, latched, base frame:
  markers.py draws the sensor frame, its uncertainty, the samples and the next pose for RViz),
  with publish_tf:=true also on /tf_static (frame-safe), and the status on
  `/diagnostics` (diagnostics.py) every diagnostics_period_s;
- serves `~/capture`, `~/reset` and `~/save` (std_srvs/Trigger);
- keeps the session's files and warnings through files/session_record.py: each captured
  sample goes to the samples journal before its estimate is published and is fsync'd before it
  is logged; resume:=true continues a journal; a moved marker is warned of once; what
  happens is logged by event_log.EventLog;
- declares its parameters from the settings table (parameters.py) and re-estimates from the
  samples kept when one that shapes the session changes at runtime.

Times come from header stamps and the node clock (so use_sim_time and bag replays work).
"""

from dataclasses import replace
import re

from diagnostic_msgs.msg import DiagnosticArray
from geometry_msgs.msg import PoseStamped
from geometry_msgs.msg import QuaternionStamped
from geometry_msgs.msg import TransformStamped
from quatcal_ros.core import conventions
from quatcal_ros.core.planner import plan_next_pose
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.validation import published
from quatcal_ros.files import journal
from quatcal_ros.files.session_record import MoveWatch, SamplesJournal, save_result
from quatcal_ros.files.text_input import BadInputError
from quatcal_ros.ros import command_line
from quatcal_ros.ros import conversions
from quatcal_ros.ros import markers
from quatcal_ros.ros import parameters
from quatcal_ros.ros import spin
from quatcal_ros.ros.diagnostics import calibrator_status, InputWatch, never_still, \
    skipped_text, status_name, still_advice
from quatcal_ros.ros.event_log import EventLog
from quatcal_ros.ros.image_samples import ImageSamples
from quatcal_ros.ros.inputs import NodeInputs
from quatcal_ros.ros.qos import DIAGNOSTICS_QOS, LATCHED_QOS, quiet_publisher_events
from quatcal_ros.ros.static_tf import broadcast_advice, StaticTf
from quatcal_ros.stream import arrival_lag
from quatcal_ros.stream import frame_notices
from quatcal_ros.stream import settings
from quatcal_ros.stream import tf_joint
from quatcal_ros.stream.log_throttle import StandingLog
from quatcal_ros.stream.message_checks import LINK, SENSOR, STALE_AFTER_S
from quatcal_ros.stream.session import EstimateUpdated, SampleCaptured, Session
from quatcal_ros.stream.settings import ConfigError, easy_handeye2_frames
from quatcal_ros.stream.tf_tree import normalize_frame
from quatcal_ros.vision.board import read_board
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock, ClockType
from rclpy.node import Node
from std_msgs.msg import Bool, Header
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

NODE_NAME = settings.NODE_NAME
# The message checks' stream names and the session's.
SESSION_STREAMS = {LINK: 'link', SENSOR: 'sensor'}
# A TF input problem (a frame not in the tree) standing this long (steady clock) is logged.
TF_PROBLEM_LOG_S = 5.0
# ... and so is a silent or stale pose stream, or publishers of the wrong type.
INPUT_PROBLEM_LOG_S = 5.0


def journal_header(config, tree=None, recorded=None):
    """
    Return the journal's first line: setup, frames, invert_sensor, TF joint, time offsets.

    tree: with TF input, the TF tree; its static chain above the sensor frame is recorded
    (tf_joint.static_chain), else the one of `recorded` (the journal's header now), if any,
    while it is the same sensor frame's: a resumed node before the driver's /tf_static.
    The sensor time offsets are those `recorded` lists (its samples were paired with them;
    the node adds one with the first sample paired with it: JournalHeader.paired_with), or
    the parameter's for a new journal.
    """
    frames = config.result_frames
    header = journal.JournalHeader(
        config.setup, *frames, config.invert_sensor,
        sensor_time_offsets=(recorded.sensor_time_offsets if recorded is not None
                             else (config.sensor_time_offset_s,)))
    if tree is None:
        return header
    chain = tf_joint.static_chain(*frames, tree)
    if chain is None and recorded is not None and recorded.sensor_frame == frames[1]:
        chain = recorded.static_chain
    return replace(header, static_chain=chain)


def without_numbers(text):
    """Return `text` with each number replaced by '#': a problem known whatever its seconds."""
    return re.sub(r'[0-9][0-9.]*', '#', text)


class CalibratorNode(Node):
    """The `calibrator` node (module docstring); raises ConfigError on bad parameters."""

    def __init__(self, **kwargs):
        # (undeclared names reach _check_parameters, which names them: rclpy's refusal did not)
        super().__init__(NODE_NAME, allow_undeclared_parameters=True, **kwargs)
        try:
            self.config = parameters.declare_parameters(self)
            self._tf_frames = settings.tf_frames(self.config)
            if self.config.sensor_input == 'image':   # before the journal moves a file aside
                read_board(self.config.board_file)
            self.journal = SamplesJournal(self.config.samples_file, journal_header(self.config),
                                          self.config.resume,
                                          origins=self.config.result_frame_origins)
        except (journal.JournalRefused, OSError) as error:
            self.destroy_node()
            raise ConfigError(f'samples_file {self.config.samples_file}: {error}') from None
        except BadInputError as error:
            self.destroy_node()
            raise ConfigError(str(error)) from None
        except ConfigError:
            self.destroy_node()
            raise
        self.log = EventLog(self.get_logger())
        self.moves = MoveWatch()
        self.images = None   # image_samples.ImageSamples with sensor_input:=image
        self.published = None   # with images: the estimate refined on the corners
        if self.config.sensor_input == 'image':
            try:
                self.images = ImageSamples(self.config, settings.session_config(self.config),
                                           self.journal.path)
            except (BadInputError, OSError) as error:
                self.destroy_node()
                raise ConfigError(str(error)) from None
            self.log.messages(self.images.messages)
        self.session = self._new_session()
        self.inputs = NodeInputs(
            self, settings.check_config(self.config), self._tf_frames,
            settings.pose_types(self.config), self._add_pose,
            None if self.images is None
            else (self.images.sensor, self.config.image_transport, self._on_new_camera),
            self._add_poses)
        self.next_pose = None   # the planner's proposal for the latest estimate
        self._newest_stamp = {}   # stream: (its latest stamp, the node clock when it came)
        self._lags = arrival_lag.ArrivalLag()   # the streams' clocks, from arrival times
        self._lags_jumps = 0   # the session's time jumps when the lags started
        # Problems logged once (besides /diagnostics): each frame notice once; the clock
        # warning (its offset changes) once while it stands; a TF input problem (its list of
        # frames changes) once it has stood TF_PROBLEM_LOG_S, while it stands.
        self._frames_log = StandingLog(forget=False)
        self._clock_log = StandingLog(key=lambda text: 'clocks')
        self._still_log = StandingLog(key=lambda text: 'never still')
        self._name_log = StandingLog(key=lambda text: 'name')
        # A silent or stale stream, publishers of the wrong type: logged once they have stood
        # INPUT_PROBLEM_LOG_S (their texts carry the seconds since: keyed without numbers).
        self._input_log = StandingLog(INPUT_PROBLEM_LOG_S * 1e9, key=without_numbers)
        self._tf_log = StandingLog(TF_PROBLEM_LOG_S * 1e9,
                                   key=lambda text: text.split(':', 2)[1])
        self._frames = {}   # stream: its latest (header, child) frames judged (_frame_problems)
        self.next_pose_publisher = self.create_publisher(
            PoseStamped, '~/next_pose', LATCHED_QOS, event_callbacks=quiet_publisher_events())
        self.markers_publisher = self.create_publisher(
            MarkerArray, '~/markers', LATCHED_QOS, event_callbacks=quiet_publisher_events())
        self.rotation_publisher = self.create_publisher(
            QuaternionStamped, '~/rotation', LATCHED_QOS,
            event_callbacks=quiet_publisher_events())
        self.transform_publisher = self.create_publisher(
            TransformStamped, '~/transform', LATCHED_QOS,
            event_callbacks=quiet_publisher_events())
        # whether the estimate on ~/rotation and ~/transform may be used (its `usable`): they
        # carry one that says not to use it too, with nothing in the message to tell
        self.usable_publisher = self.create_publisher(
            Bool, '~/usable', LATCHED_QOS, event_callbacks=quiet_publisher_events())
        self.static_tf = StaticTf(self)
        self._broadcast_convention = None   # (setup, invert_sensor) of the estimate latched
        if self.inputs.tf is not None:   # our broadcast heard back gives way to another's
            self.inputs.tf.ours = self.static_tf.sent
            self.inputs.tf.on_ours_replaced = self._rebroadcast
        self.diagnostics_publisher = self.create_publisher(
            DiagnosticArray, '/diagnostics', DIAGNOSTICS_QOS,
            event_callbacks=quiet_publisher_events())
        # On the node clock (with use_sim_time: one status per second of a played bag); a
        # steady-clock watch keeps it coming, saying so, when that clock stands still.
        self.create_timer(self.config.diagnostics_period_s, self.publish_diagnostics)
        self._steady = Clock(clock_type=ClockType.STEADY_TIME)
        self._last_status_ns = self._steady.now().nanoseconds
        self.create_timer(self.config.diagnostics_period_s, self._watch_status,
                          clock=self._steady)
        self.create_service(Trigger, '~/capture', self._on_capture)
        self.create_service(Trigger, '~/reset', self._on_reset)
        self.create_service(Trigger, '~/save', self._on_save)
        # (after every declaration: a later declare_parameter reaches _check_parameters too,
        # which refuses a name not yet declared)
        self.add_on_set_parameters_callback(self._check_parameters)
        self.add_post_set_parameters_callback(self._apply_parameters)
        self.get_logger().info(
            f'calibrating the {self.config.setup} mounting '
            f'{" -> ".join(self.config.result_frames)} from {self.inputs.describe()}, '
            f'capture mode {self.config.capture_mode}')
        self._start_tf_broadcast()
        self.input_watch = InputWatch(self.inputs.type_names, self.now_ns(), self.inputs.reliable)
        self._resume()

    @property
    def stats(self):
        """Return the message counts (message_checks.StreamStats)."""
        return self.inputs.screen.stats

    @property
    def checks(self):
        """Return what pose messages must satisfy (message_checks.CheckConfig)."""
        return self.inputs.screen.config

    def now_ns(self):
        """Return the node clock (ROS time; simulated with use_sim_time) in nanoseconds."""
        return self.get_clock().now().nanoseconds

    def stamps_now_ns(self):
        """
        Return the time now on the clock of the poses' stamps (the session's clock).

        The latest stamp of a stream plus the node time since it came (the later of the two
        streams'; the sensor's with sensor_time_offset_s): stamps a second or more behind
        the node clock (a slow detector, another machine's clock) are recent all the same.
        The node clock itself before any pose.
        """
        now_ns = self.now_ns()
        offsets = {LINK: 0, SENSOR: self.session.config.sensor_offset_ns}
        return max((stamp_ns + offsets[stream] + now_ns - came_ns
                    for stream, (stamp_ns, came_ns) in self._newest_stamp.items()),
                   default=now_ns)

    def _note_stamp(self, stream, stamp_ns, now_ns):
        self._newest_stamp[stream] = (stamp_ns, now_ns)   # the latest (after a time jump too)
        self._lags.note(stream, stamp_ns, now_ns)

    def _add_pose(self, stream, taken, now_ns):
        """Give a checked (stamp_ns, Pose) to the session; handle what it says."""
        self._note_stamp(stream, taken[0], now_ns)
        add = self.session.add_link_pose if stream == LINK else self.session.add_sensor_pose
        events = self.inputs.screen.verdict(stream, add(*taken), now_ns,
                                            held=self.session.held)
        if events:
            self.handle_events(events)

    def _add_poses(self, stream, stamps_ns, positions, quaternions_wxyz, now_ns):
        """Give a run of checked poses of one stream to the session at once (add_poses)."""
        self._note_stamp(stream, stamps_ns[-1], now_ns)
        events = self.inputs.screen.verdict(
            stream, self.session.add_poses(SESSION_STREAMS[stream], stamps_ns, positions,
                                           quaternions_wxyz), now_ns, count=len(stamps_ns),
            held=self.session.held)
        if events:
            self.handle_events(events)

    # --- session events --------------------------------------------------------------------

    def handle_events(self, events):
        """
        Journal new samples, publish each new estimate, then log the session's events.

        The journal comes first: a sample is in the file (safe from a crash of the process)
        before the estimate is published, and fsync'd (safe from a power cut) before it is
        reported captured. The log lines come last; then the session is asked for the estimate
        of the new samples, whose events are handled the same way.
        """
        captured = [event.sample for event in events if isinstance(event, SampleCaptured)]
        if captured:   # the sensor time offset they have; the TF joint, once the tree shows it
            header = self.journal.header if self.inputs.tf is None else self._journal_header()
            self.log.messages(self.journal.set_header(header.paired_with(
                self.config.sensor_time_offset_s, kept=self.journal.count > 0)))
        self.log.messages(self.journal.append(captured, self.session.samples))
        if self.images is not None:
            self.log.messages(self.images.keep(captured))
            events = [EstimateUpdated(self._on_pixels(event.result))
                      if isinstance(event, EstimateUpdated) else event for event in events]
        for event in events:
            if isinstance(event, EstimateUpdated):
                self.publish_estimate(event.result)
        if captured:
            self.log.messages(self.journal.sync())
            if self.images is not None:
                self.log.messages(self.images.sync())
        self.log.log(events, self._move_check, self.journal.saved)
        # The estimate of new samples, if any (the session estimates when asked).
        later = self.session.estimate()
        if later:
            self.handle_events(later)

    def _new_session(self):
        """Return a Session of the settings; with images, each sample keeps its corners."""
        config = self._session_config()
        if self.images is None:
            return Session(config)
        return Session(config, on_sample=self.images.sensor.keep)

    def _session_config(self):
        """Return the SessionConfig of the settings; the image sensor, if any, follows it."""
        config = settings.session_config(self.config)
        if self.images is not None:   # (its still window, its averaging, its time offset)
            self.images.sensor.configure(config)
        return config

    def _on_pixels(self, result):
        """Return the result to publish: with sensor_input:=image refined on the corners."""
        if self.images is None:
            return result
        options = self.session.config.calibration
        refined = self.images.on_pixels(self.session.samples, result, options.setup,
                                        options.robust)
        self.published = refined or result
        return self.published

    def _on_new_camera(self, changed):
        """Estimate on the pixels again: the first or (changed) new intrinsics arrived."""
        if changed:   # the corners kept were measured with the old ones
            self.log.messages(self.images.camera_changed())
        if self.session.result is not None:
            self.handle_events([EstimateUpdated(self.session.result)])

    @property
    def result(self):
        """Return the published estimate: the session's, or on the pixels (image input)."""
        if self.images is None or self.session.result is None:
            return self.session.result
        return self.published

    def _move_check(self, result):
        options = self.session.config.calibration
        return self.moves.check(self.session.samples, result.quaternion, options.setup,
                                options.invert_sensor)

    def publish_estimate(self, result):
        """Publish `result` (quaternion, translation) on ~/rotation, ~/transform, /tf_static."""
        msg = conversions.quaternion_stamped_msg(
            result.quaternion, self.now_ns(), self.config.result_frames[0])
        self.usable_publisher.publish(Bool(data=bool(result.usable)))   # (first: read with it)
        self.rotation_publisher.publish(msg)
        stamp_ns = conversions.stamp_ns_from_header(msg.header)
        self.transform_publisher.publish(self.transform_msg(result, stamp_ns))
        if self.config.publish_tf:
            self._broadcast(result, stamp_ns)
        options = self.session.config.calibration
        self.next_pose = plan_next_pose(self.session.samples, result, options.setup,
                                        options.invert_sensor, settings.plan_limits(self.config))
        if self.next_pose is not None:
            self.next_pose_publisher.publish(conversions.pose_stamped_msg(
                self.next_pose.link, stamp_ns, self._base_frame()))
        samples = self.session.samples
        self.markers_publisher.publish(markers.calibration_markers(
            result, samples, result.sample_states(len(samples)), self.next_pose,
            options.setup, Header(stamp=msg.header.stamp, frame_id=self._base_frame())))

    def _base_frame(self):
        """Return the robot base frame: the TF input's, the link poses' header, or base_link."""
        if self._tf_frames is not None:
            return self._tf_frames[LINK][0]
        if self.config.link_frame_id:
            return self.config.link_frame_id
        return self.config.result_frames[0] if self.config.setup == 'eye_to_hand' else 'base_link'

    def transform_msg(self, result, stamp_ns):
        """Return the TransformStamped of `result` between the result frames."""
        return conversions.transform_stamped_msg(
            Pose.create(result.translation, result.quaternion), stamp_ns,
            *self.config.result_frames)

    def _start_tf_broadcast(self):
        """
        With publish_tf, start /tf_static; turned on at runtime, it sends the estimate.

        Turned off, the latched transform is withdrawn for listeners that join later.
        """
        result = self.result
        if not self.config.publish_tf:
            self.static_tf.withdraw()
        elif self.static_tf.start() and result is not None:
            self._broadcast(result, self.now_ns())

    def _rebroadcast(self):
        """Broadcast the last transform sent again: its frames' parents in TF changed."""
        if self.config.publish_tf:
            self.static_tf.resend(self.inputs.tf.tree)

    def _broadcast(self, result, stamp_ns):
        """
        Put the result on /tf_static, frame-safe in the TF tree with TF input.

        Not before the frame convention is checked (3 samples fit every one alike: a wrong
        setup's estimate was latched, 176 deg off, and kept when sample 4 found it wrong). A
        convention found wrong withdraws what was latched under it (not one latched under
        another setup before a change at runtime). Any other warning that says not to use it
        leaves the last usable one latched.
        """
        options = self.session.config.calibration
        convention = (options.setup, options.invert_sensor)
        if conventions.unchecked(result.warnings):
            self.static_tf.hold(f'publish_tf: the frame convention is checked from '
                                f'{conventions.CHECKED_FROM_SAMPLES} samples on: nothing is '
                                'broadcast until then', 'the frame convention is not checked',
                                problem=False)
            return
        if not result.usable:
            if (any(text.startswith(conventions.PREFIX) for text in result.warnings)
                    and self._broadcast_convention == convention):
                self.static_tf.withdraw()
                self.static_tf.hold('publish_tf: the frame convention fits badly (on '
                                    '/diagnostics): the estimates broadcast were made with it, '
                                    'so none stays on /tf_static')
                return
            self.static_tf.hold('publish_tf: the estimate says not to use it (its warnings, '
                                'on /diagnostics): the last one without such a warning stays '
                                'on /tf_static')
            return
        self._broadcast_convention = convention
        self.static_tf.send(Pose.create(result.translation, result.quaternion), stamp_ns,
                            *self.config.result_frames,
                            self.inputs.tf.tree if self.inputs.tf is not None else None)

    # --- samples journal -------------------------------------------------------------------

    def _journal_header(self):
        """Return the journal's first line for the parameters and the TF tree now."""
        return journal_header(self.config,
                              self.inputs.tf.tree if self.inputs.tf is not None else None,
                              self.journal.header)

    def _resume(self):
        """Log what opening the journal did; estimate from its samples when resuming."""
        report = self.journal.report
        self.log.messages(report.messages)
        self._resume_tf_joint()
        if self.images is not None:
            self.log.messages(self.images.restore(report.samples))
        if report.samples:   # already in the journal: not appended again, not logged
            self._add_known_samples(report.samples)
            if self.session.result is None:
                self.get_logger().info(f'no estimate from the resumed samples yet: '
                                       f'{self.session.last_error}')

    def _resume_tf_joint(self):
        """
        Start the TF tree with a resumed journal's static chain (JournalHeader.static_chain).

        Until the camera driver's /tf_static comes, the result's joint (~/save, publish_tf)
        would else be link -> sensor frame: pasted or broadcast, a second parent.
        """
        recorded, sensor_frame = self.journal.header, self.config.result_frames[1]
        if (self.inputs.tf is None or recorded.static_chain is None
                or recorded.sensor_frame != sensor_frame
                or self.inputs.tf.tree.parent(sensor_frame) is not None):
            return
        self.inputs.tf.assume_static_chain(sensor_frame, recorded.static_chain)
        self.get_logger().info(
            f'the journal says {sensor_frame} hangs below {recorded.static_chain[0]} in TF: '
            'the result joins the tree there until /tf_static says otherwise')

    def _add_known_samples(self, samples):
        events = self.session.add_samples(samples)
        self.handle_events([e for e in events if not isinstance(e, SampleCaptured)])

    def destroy_node(self):
        """Take the link poses held, close the journal (releasing its lock), destroy the node."""
        if getattr(self, 'inputs', None) is not None and getattr(self, 'journal', None):
            self.inputs.flush()
        if getattr(self, 'journal', None) is not None:
            self.journal.close()
            self.journal = None
        if getattr(self, 'images', None) is not None:
            self.images.close()
            self.images = None
        return super().destroy_node()

    # --- diagnostics -----------------------------------------------------------------------

    def diagnostic_status(self):
        """Build the DiagnosticStatus published on /diagnostics."""
        tf_static, tf_problem = self.static_tf.state(self.config.publish_tf)
        self.inputs.check_publishers()
        now_ns = self.now_ns()
        watched = self.input_watch.problems(
            self.stats, self.inputs.topics, self.get_publishers_info_by_topic,
            self.session.counters['time_jumps'], now_ns,
            self.get_parameter('use_sim_time').value, self._steady.now().nanoseconds)
        stale = self.stats.stale_reasons(now_ns, STALE_AFTER_S, self.input_watch.started_ns,
                                         self.inputs.topics, self.inputs.composed)
        # (/diagnostics alone said that nothing came on a pose topic: the log stayed silent)
        explained = self.input_watch.explained   # (a wrong type: not 'does it run?')
        self._log_standing(self._input_log, [*dict.fromkeys(text for stream, text in stale
                                                            if stream not in explained),
                                             *watched])
        # (a sensor too noisy for its still bands showed on /diagnostics alone)
        stuck = never_still(self.session)
        self._log_standing(self._still_log, [stuck and f'{stuck}: {still_advice(self.session)}'])
        problems = [self.moves.warning(len(self.session.samples)), self.journal.problem,
                    tf_problem, *watched, *self._input_problems(), *self._frame_problems(),
                    self._clock_problem(), self._name_problem()]
        return calibrator_status(self.session, self.stats, now_ns,
                                 self.config.result_frames[0], problems, tf_static,
                                 self.input_watch.started_ns, self.inputs.topics,
                                 self.next_pose, self.result, self.inputs.composed,
                                 status_name(self.get_name()), explained)

    def _input_problems(self):
        """
        Return the TF input's problems; log each once it has stood for TF_PROBLEM_LOG_S.

        A misspelt frame showed on /diagnostics alone: the log stayed silent. Not at once:
        the frames of /tf_static and /tf come in over the first second or two.
        """
        found = self.inputs.problems(self.session.result)
        self._log_standing(self._tf_log, found)
        return found

    def _log_standing(self, log, texts):
        """Log as warnings those of the problems `texts` that the StandingLog `log` says."""
        for text in log.due([text for text in texts if text], self._steady.now().nanoseconds):
            self.get_logger().warning(text)

    def _settle_held(self):
        """Count a pose the old session held undecided, which the new one never saw (good)."""
        self.inputs.screen.verdict(LINK, [], count=0, held=self.session.held)

    def _name_problem(self):
        """
        Return the problem of another node of this name on the domain (logged once), or None.

        Its services and parameters answer at the same names: ~/save, ~/reset or a parameter
        change may reach either (two of one name ran side by side without a word).
        """
        me = (self.get_name(), self.get_namespace())
        others = self.get_node_names_and_namespaces().count(me) - 1
        text = None
        if others > 0:
            name = self.get_fully_qualified_name()
            text = (f'{others} other node(s) named {name} run on this ROS domain: ~/save, '
                    '~/reset and parameter changes may reach either; give each calibrator a '
                    f'name of its own (--ros-args -r __node:={self.get_name()}_2)')
        self._log_standing(self._name_log, [text])
        return text

    def _clock_problem(self):
        """Return arrival_lag's warning on the streams' clocks (logged once), or None."""
        jumps = self.session.counters['time_jumps']
        if jumps != self._lags_jumps:   # a bag looped: the lags of the old timeline mislead
            self._lags, self._lags_jumps = arrival_lag.ArrivalLag(), jumps
        self._lags.end_period()
        configured = self.session.config.sensor_offset_ns
        text = arrival_lag.problem(self._lags.offset_ns(configured), configured)
        self._log_standing(self._clock_log, [text])
        return text

    def _frame_problems(self):
        """
        Return frame_notices' warnings on the input messages' frames; log each text once.

        The frames of each stream's first message since the last status (else those seen
        before it, for a stream silent since): a publisher put right clears its warning.
        """
        config = self.config
        self._frames.update(self.inputs.frames_seen)
        self.inputs.frames_seen.clear()   # the next status takes each stream's next message
        seen = dict(self._frames)
        for stream, expected in ((LINK, config.link_frame_id), (SENSOR, config.sensor_frame_id)):
            if expected and stream in seen:   # the messages used carry exactly this frame
                seen[stream] = (normalize_frame(expected), seen[stream][1])
        said = frame_notices.notices(seen, config.setup, config.invert_sensor,
                                     tuple(map(normalize_frame, config.result_frames)))
        self._log_standing(self._frames_log, said)
        return said

    def _watch_status(self):
        """Publish the status when the node clock has not for two periods (no /clock)."""
        self.inputs.flush()   # the link poses held, even when the node clock stands still
        late_ns = 2 * self.config.diagnostics_period_s * 1e9
        if self._steady.now().nanoseconds - self._last_status_ns > late_ns:
            self.publish_diagnostics()

    def publish_diagnostics(self):
        """Publish the status once (the timer's callback)."""
        self.inputs.flush()
        self._last_status_ns = self._steady.now().nanoseconds
        array = DiagnosticArray(status=[self.diagnostic_status()])
        array.header.stamp = self.get_clock().now().to_msg()
        self.diagnostics_publisher.publish(array)

    # --- services --------------------------------------------------------------------------

    def _on_capture(self, request, response):
        self.inputs.flush()
        ok, reason = self.session.capture(self.stamps_now_ns())
        self.handle_events(self.session.pop_events())
        unpaired = not ok and reason.startswith('no paired poses')
        skipped = skipped_text(self.stats)
        if unpaired and skipped:
            reason += f' (so far {skipped})'   # (no board, other units): not the clocks
        if unpaired and self.inputs.tf is not None:   # a frame missing names itself
            reason += ''.join(f' ({problem})' for problem in self.inputs.tf.problems(
                self.session.result))
        if not ok:
            self.log.capture_refused(reason)
        response.success, response.message = bool(ok), reason
        return response

    def _on_reset(self, request, response):
        self.inputs.flush()
        discarded = len(self.session.samples)
        self.session.reset()
        self._settle_held()
        self.stats.start_session()
        self._lags, self._lags_jumps = arrival_lag.ArrivalLag(), 0
        self.log.reset()
        self.moves.reset()
        self.next_pose = None
        journal_text = self.journal.restart(   # (its samples: all paired with the offset now)
            self._journal_header().paired_with(self.config.sensor_time_offset_s, kept=False))
        self.static_tf.new_session()
        self.markers_publisher.publish(markers.clear_markers(
            Header(stamp=self.get_clock().now().to_msg(), frame_id=self._base_frame())))
        if self.images is not None:
            journal_text += self.images.restart()
        if self.journal.problem:
            self.get_logger().error(self.journal.problem)
        response.success = True
        response.message = (f'session cleared: the new one starts without the {discarded} '
                            'samples (what is latched stays until a new estimate: ~/rotation, '
                            f'~/transform, ~/next_pose, /tf_static){journal_text}')
        self.get_logger().info(response.message)
        return response

    def _on_save(self, request, response):
        self.inputs.flush()
        self.handle_events(self.session.full_estimate())   # as `solve` of the journal gives
        result = self.result
        if result is None:
            response.success = False
            response.message = f'no estimate yet, nothing saved: {self.session.last_error}'
            return response
        config = self.config
        frames = config.result_frames
        # As the tools save it: frames given swapped (the right fix) before the setup advice
        # they look like, a failed validation said.
        result = published(result, causes=(self.inputs.tf.swapped_frames(result)
                                           if self.inputs.tf is not None else ()))
        mount = tf_joint.joint(result, frames,
                               self.inputs.tf.tree if self.inputs.tf is not None else None)
        saved = save_result(result, frames, config.setup, config.result_file,
                            config.easy_handeye2_file, easy_handeye2_frames(config),
                            joint=mount)
        response.success, response.message = saved.ok, '; '.join(saved.texts())
        if saved.ok and not result.usable:   # (first: the reply runs past a kilobyte)
            response.message = ('saved an estimate that says not to use it ("usable": false '
                                f'in the file): {response.message}')
        if not saved.ok:
            self.get_logger().error(response.message)
        if saved.ok and result.warnings:   # saved as asked, but not without a word
            response.message += (f'; the estimate has {len(result.warnings)} warning(s), in '
                                 f'the file too: {" | ".join(result.warnings)}')
            self.get_logger().warning(f'result {response.message}')
        elif saved.ok:
            self.get_logger().info(f'result {response.message}')
            self.get_logger().info(broadcast_advice(mount))
        return response

    # --- parameters at runtime -------------------------------------------------------------

    def _check_parameters(self, changes):
        self.inputs.flush()
        unknown = command_line.unknown_at_runtime(self, changes, settings.SETTING_BY_NAME,
                                                  NODE_NAME)
        if unknown:
            return SetParametersResult(successful=False, reason=unknown)
        try:
            parameters.updated(self.config, changes)
        except ConfigError as error:
            return SetParametersResult(successful=False, reason=str(error))
        return SetParametersResult(successful=True)

    def _apply_parameters(self, changes):
        old, self.config = self.config, parameters.updated(self.config, changes)
        self.inputs.screen.config = settings.check_config(self.config)
        changed = [n for n, v in self.config.as_dict().items() if old.as_dict()[n] != v]
        if changed:
            self.get_logger().info(f'parameters changed: {", ".join(changed)}')
            # The header follows setup, the result frames and invert_sensor (set_header writes
            # only a new one).
            self.log.messages(self.journal.set_header(self._journal_header()))
        if 'publish_tf' in changed:
            self._start_tf_broadcast()
        if 'capture_mode' in changed and self.config.capture_mode == 'continuous':
            self.moves.capture_continuous(len(self.session.samples))
        if any(name not in settings.PRESENTATION + settings.CAPTURE for name in changed):
            samples = self.session.samples
            earlier, self.session = self.session, self._new_session()
            self.session.continue_counts(earlier)
            self._settle_held()
            self.next_pose = None   # the re-estimate plans again, if there is one
            if samples:
                self.get_logger().info(
                    f're-estimating from the {len(samples)} samples with the new settings')
                if 'sensor_time_offset_s' in changed:   # (samples keep the poses they paired)
                    self.get_logger().warn(
                        f'sensor_time_offset_s applies to the poses from now on: the '
                        f'{len(samples)} samples taken keep the pairing they were taken with; '
                        'call ~/reset to take them again with the new offset')
                self._add_known_samples(samples)
        else:
            if any(name in settings.CAPTURE for name in changed):   # (the estimate stays)
                self.session.set_capture(self._session_config().capture)
            # the same estimate, between the new frames (eye_to_hand's parent follows
            # link_frame_id while link_frame is left at its default)
            if old.result_frames != self.config.result_frames and self.result is not None:
                self.publish_estimate(self.result)


def main(args=None):
    """Run the calibrator node; return 2 (after logging the reason) for invalid parameters."""
    return spin.run(CalibratorNode, NODE_NAME, ConfigError, 'invalid parameters', args,
                    parameters.command_line_problem)


if __name__ == '__main__':
    raise SystemExit(main())
