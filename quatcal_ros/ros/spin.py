"""
Run a node until SIGINT or SIGTERM, and end with exit status 0: the package's nodes share this.

No KeyboardInterrupt is raised: one raised while rclpy converts a message in C++ comes out as a
RuntimeError from take_message (seen in CI), not as KeyboardInterrupt.  The handlers shut rclpy
down, which wakes the executor; rclpy's own handlers (installed by rclpy.init after these, and
chaining to them) do the same.  A signal before rclpy.init is remembered and honoured as soon
as rclpy is up.
"""

import gc
import os
import signal
import sys
import tempfile
import threading

from quatcal_ros.ros import stop_signals
import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.executors import SingleThreadedExecutor
from rclpy.utilities import get_default_context


def install_stop_handlers():
    """
    Make SIGINT and SIGTERM shut rclpy down; return the list of signals received.

    Signals noted before (stop_signals.guard, from the entry point on) are in the list.
    """
    received = stop_signals.received

    def on_signal(signum, frame):
        received.append(signum)
        # The handler runs in the main thread between two of its bytecodes, maybe inside
        # rclpy's Context.ok(), which holds the lock try_shutdown takes (a non-reentrant
        # threading.Lock): shutting down here then hung the process (about once in 50 stops,
        # seen in CI). When the main thread holds it, a thread shuts down as soon as it lets
        # go; otherwise here and now, so that what the main thread does next sees rclpy down.
        lock = getattr(get_default_context(), '_lock', None)
        if lock is not None and not lock.acquire(blocking=False):
            threading.Thread(target=_shutdown, name='stop-signal', daemon=True).start()
            return
        if lock is not None:
            lock.release()
        _shutdown()
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, on_signal)
    return received


def _shutdown():
    try:
        rclpy.try_shutdown()
    except RuntimeError:   # RCLError: rclpy's own handler shut the context down meanwhile
        pass


def start(make_node, refused=()):
    """
    Make the executor and the node; (None, None) when a stop signal came meanwhile.

    Exceptions of the types in `refused` (the node's own start-up errors) pass through.
    """
    if not rclpy.ok():   # a signal came first: build nothing on a context that is down
        return None, None
    try:
        return SingleThreadedExecutor(), make_node()
    except refused:
        raise
    except KeyboardInterrupt:
        rclpy.try_shutdown()
        return None, None
    except Exception:   # noqa: B902 - whatever rclpy raises once a signal shut it down
        if rclpy.ok():
            raise
        return None, None


def spin_until_stopped(node, executor):
    """
    Spin `node` until rclpy shuts down, then destroy it and shut rclpy down.

    An explicit executor: rclpy.spin's global one cannot be made once a signal has shut the
    context down.  A signal between two executor steps makes the next step fail with RCLError
    ('the given context is not valid', seen in CI) instead of ExternalShutdownException:
    with the context down, that is the same stop.
    """
    # Everything made so far lives as long as the process: keep it out of the cyclic
    # collector, whose full passes over it took ~0.1 s on a sample's callback.
    gc.freeze()
    try:
        rclpy.spin(node, executor=executor)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except RuntimeError:   # RCLError
        if rclpy.ok():
            raise
    finally:
        node.destroy_node()
        rclpy.try_shutdown()


def run(make_node, default_name, refused, what, args=None, command_line=None):
    """
    Run the node `make_node` builds until a stop signal: the main() of the package's nodes.

    A start-up error of a type in `refused` is logged as FATAL under the node's name (the
    default_name, or as remapped with __node:=NAME) as '<what>: <error>', and gives 2.
    command_line(arguments): (exit status, text) when the node must not start (its --help,
    an argument it does not take), else None; the text goes to stdout for status 0.
    :return: 0 after a stop signal, 2 after a refused start.
    """
    if command_line is not None:
        said = command_line(sys.argv if args is None else args)
        if said is not None:
            status, text = said
            try:
                print(text if status == 0 else f'{default_name}: error: {text}',
                      file=sys.stdout if status == 0 else sys.stderr)
            except BrokenPipeError:   # `--help | head`: the reader left
                os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            return status
    stopped = install_stop_handlers()
    _ensure_log_directory()
    rclpy.init(args=args)
    if stopped:
        rclpy.try_shutdown()
    try:
        executor, node = start(make_node, refused)
    except refused as error:
        rclpy.logging.get_logger(node_name(args, default_name)).fatal(f'{what}: {error}')
        rclpy.try_shutdown()
        return 2
    if node is not None:
        spin_until_stopped(node, executor)
    stopped.clear()   # this run's signals, not the next one's (tests run nodes in-process)
    return 0


def _ensure_log_directory():
    """
    Give rcl a log directory when HOME is unset (a service, a container): it needs one.

    rcl writes its log files to ROS_LOG_DIR, else ROS_HOME/log, else $HOME/.ros/log; without
    any of them rclpy.init fails.  ROS_HOME then becomes the user's home from the password
    database (~/.ros), or the temporary directory; stderr says where.
    """
    if any(os.environ.get(name) for name in ('ROS_LOG_DIR', 'ROS_HOME', 'HOME')):
        return
    home = os.path.expanduser('~')
    base = home if home != '~' and os.path.isdir(home) else tempfile.gettempdir()
    os.environ['ROS_HOME'] = os.path.join(base, '.ros')
    print(f'HOME is not set: ROS_HOME is {os.environ["ROS_HOME"]} (rcl writes its log files '
          'there)', file=sys.stderr)


def node_name(args, default_name):
    """Return the node name as remapped on the command line (-r __node:=NAME), or the default."""
    args = sys.argv if args is None else args
    for before, arg in zip(args, args[1:]):
        if before in ('-r', '--remap') and arg.startswith(('__node:=', '__name:=')):
            return arg.split(':=', 1)[1]
    return default_name
