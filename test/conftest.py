"""
Fixtures and settings shared by all tests of quatcal_ros.

Before any test module is imported, pytest_configure points HOME, ROS_HOME and ROS_LOG_DIR at
a temporary directory of this session (nodes built by module-scoped fixtures, rcl's log files
and every subprocess land there) and reserves a ROS domain id of this host for the session's
default ROS_DOMAIN_ID.  Each test gets a private HOME on top (private_home).  At the end the
user's own ~/.ros directories are compared with what they held at the start: a test that
wrote there fails the session, naming what changed. The rcl log files that other processes
(a ROS system running beside the tests) write there meanwhile are only reported: rcl names
them after their process, and the session knows its own (this one and those it started).
"""

import os
from pathlib import Path
import shutil
import subprocess
import sys
import tempfile

from hypothesis import HealthCheck, settings
from hypothesis.configuration import set_hypothesis_home_dir
import pytest
from quatcal_ros.core.pose import Pose
import ros_domains
import user_files

REPO_ROOT = Path(__file__).resolve().parents[1]
SESSION = pytest.StashKey[dict]()

# Nodes started by the tests (in-process or as subprocesses, which inherit this) talk over real
# DDS: keep discovery on this machine so parallel runs and other hosts do not interfere (an
# inherited SUBNET or static peers would reach past the host-local domain reservation).
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.pop('ROS_STATIC_PEERS', None)

# Property-based tests: the same examples on every run, no example database (it would live in
# the working directory); `HYPOTHESIS_PROFILE=explore` searches ten times wider at random.
settings.register_profile(
    'default', derandomize=True, database=None, deadline=None, print_blob=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                           HealthCheck.data_too_large])
settings.register_profile(
    'explore', database=None, deadline=None, max_examples=1000, print_blob=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                           HealthCheck.data_too_large])
settings.load_profile(os.environ.get('HYPOTHESIS_PROFILE', 'default'))


def pytest_configure(config):
    """Move HOME, ROS_HOME and ROS_LOG_DIR to a session directory; reserve ROS_DOMAIN_ID."""
    watched = user_files.watched_dirs(os.environ)
    home = Path(tempfile.mkdtemp(prefix='quatcal_ros-test-home-'))
    config.stash[SESSION] = {
        'watched': watched, 'before': user_files.snapshot(watched), 'home': home,
        'domain': ros_domains.reserve(), 'passed': False, 'pids': {os.getpid()},
        'popen_init': subprocess.Popen.__init__, 'others': []}
    record_processes(config.stash[SESSION])
    os.environ['HOME'] = str(home)
    os.environ['ROS_HOME'] = str(home / '.ros')
    os.environ['ROS_LOG_DIR'] = str(home / '.ros' / 'log')
    os.environ['ROS_DOMAIN_ID'] = str(config.stash[SESSION]['domain'].domain_id)
    # Caches in the session directory, not the working tree: hypothesis's (its unicode
    # tables) and Python's bytecode of this process's later imports and of every subprocess.
    set_hypothesis_home_dir(str(home / '.hypothesis'))
    os.environ['PYTHONPYCACHEPREFIX'] = sys.pycache_prefix = str(home / 'pycache')
    sys.dont_write_bytecode = False   # (make test starts without: only until now)
    os.environ.pop('PYTHONDONTWRITEBYTECODE', None)


def record_processes(state):
    """
    Add the id of every process the session starts (subprocess.Popen) to state['pids'].

    Only direct children started through subprocess.Popen are seen (the suite starts no other
    kind); a grandchild's rcl log in the user's directory would be reported as another
    process's, not fail the run.  The tests point HOME and ROS_LOG_DIR elsewhere, so this is
    the second guard, not the first.
    """
    start = state['popen_init']

    def recorded(self, *args, **kwargs):
        start(self, *args, **kwargs)
        state['pids'].add(self.pid)
    subprocess.Popen.__init__ = recorded


def pytest_sessionfinish(session, exitstatus):
    """Note whether the session passed (its temporary HOME is then removed)."""
    if SESSION in session.config.stash:
        session.config.stash[SESSION]['passed'] = exitstatus == 0


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """After a failure, say where the session's HOME (and rcl's log files) are kept."""
    others = config.stash[SESSION]['others'] if SESSION in config.stash else []
    if others:
        terminalreporter.write_line(
            "other processes wrote rcl log files in the user's ROS log directory during the "
            "session (not the tests: their process ids are not the session's):\n  "
            + '\n  '.join(others))
    if SESSION in config.stash and exitstatus != 0:
        home = config.stash[SESSION]['home']
        terminalreporter.write_line(f'test HOME kept: {home} (rcl logs in {home}/.ros/log)')


def pytest_unconfigure(config):
    """Release the session's domain id; remove its HOME unless the session failed."""
    state = config.stash.get(SESSION, None)
    if state is None:
        return
    state['domain'].release()
    subprocess.Popen.__init__ = state['popen_init']
    if state['passed']:
        shutil.rmtree(state['home'], ignore_errors=True)


@pytest.fixture(scope='session', autouse=True)
def user_files_untouched(pytestconfig):
    """Fail the session if its processes changed the user's ~/.ros (journal, results, rcl logs)."""
    yield
    state = pytestconfig.stash[SESSION]
    changed, state['others'] = user_files.changes_of(
        state['before'], user_files.snapshot(state['watched']), state['pids'])
    if changed:
        pytest.fail("the user's own ROS files changed during the test session (a test, or "
                    'another process, wrote outside the test HOME):\n  ' + '\n  '.join(changed),
                    pytrace=False)


@pytest.fixture(scope='session')
def session_home(pytestconfig):
    """Return the session's temporary HOME (rcl's log files are in its .ros/log)."""
    return pytestconfig.stash[SESSION]['home']


@pytest.fixture(autouse=True)
def private_home(tmp_path_factory, monkeypatch):
    """
    Give every test (and the processes it starts) a HOME and ROS_HOME of its own.

    The calibrator node writes ~/.ros/quatcal/samples.csv (its samples journal) by default and
    moves an earlier one aside: tests must not touch the user's files, nor each other's.
    Returns the directory.
    """
    home = tmp_path_factory.mktemp('home')
    monkeypatch.setenv('HOME', str(home))
    monkeypatch.setenv('ROS_HOME', str(home / '.ros'))
    return home


@pytest.fixture(scope='module')
def domain_id():
    """Return a ROS domain id that no other holder on this host has, for one test module."""
    with ros_domains.reserve() as reservation:
        yield reservation.domain_id


@pytest.fixture(scope='module')
def process_domain_id():
    """Return a second id for one module: the processes it starts, apart from its own nodes."""
    with ros_domains.reserve() as reservation:
        yield reservation.domain_id


@pytest.fixture(scope='session')
def repo_root():
    """Return the repository root (the package directory), as a pathlib.Path."""
    return REPO_ROOT


@pytest.fixture(scope='session')
def datasets_dir():
    """
    Return the real recordings shipped with the repository (data/), as a pathlib.Path.

    Each folder has its SOURCE.md (origin, licence, format); see data/README.md.
    """
    return REPO_ROOT / 'data'


@pytest.fixture(scope='session')
def eth_streams(datasets_dir):
    """
    Return the ETH robot-arm recording as (link, camera) lists of (stamp_ns, Pose).

    Link: sr300_hinge in base_link, ~50 Hz. Camera: the IR camera in the target frame, ~30 Hz
    (SOURCE.md: the inverse of T_sensor_obj, so solve it with invert_sensor).
    """
    from quatcal_ros.files.pose_streams import read_pose_stream
    folder = datasets_dir / 'ethz_robot_arm_real'

    def load(name):
        stamps, positions, quaternions = read_pose_stream(folder / name)
        return [(s, Pose(p, q)) for s, p, q in zip(stamps, positions, quaternions)]
    return load('link_hinge_in_base.csv'), load('ir_camera_in_target.csv')
