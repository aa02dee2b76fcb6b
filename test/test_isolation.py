"""
What keeps the suite apart from other suites and from the user: domain ids and HOME.

The domain id allocator (ros_domains) is checked in an abstract-socket namespace of its own,
so that reserving every candidate id does not hold up another suite on the host; conftest's
fixtures in the real one.  Then the session's environment (HOME, ROS_HOME, ROS_LOG_DIR in a
temporary directory) and the guard of the user's files (user_files).
"""

import os
from pathlib import Path
import socket
import subprocess
import sys
import uuid

import pytest
import rclpy
import ros_domains
import user_files

HERE = Path(__file__).resolve().parent
# A child that reserves one of its argv's ids in its argv's namespace, says which, and holds
# it until its stdin closes (or it is killed).
HOLDER = """
import sys
sys.path.insert(0, sys.argv[1])
import ros_domains
try:
    reservation = ros_domains.reserve([int(d) for d in sys.argv[3:]], sys.argv[2])
except ros_domains.DomainsExhausted:
    print('exhausted', flush=True)
    raise SystemExit(3)
print(reservation.domain_id, flush=True)
sys.stdin.read()
"""


@pytest.fixture
def namespace():
    """Return an abstract-socket namespace of this test alone."""
    return f'quatcal_ros-test-domain-selftest-{os.getpid()}-{uuid.uuid4().hex[:8]}'


def start_holder(namespace, *candidates):
    """Start a child process that reserves one of `candidates`; return (process, its answer)."""
    child = subprocess.Popen(
        [sys.executable, '-c', HOLDER, str(HERE), namespace, *map(str, candidates)],
        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    return child, child.stdout.readline().strip()


def test_reservations_never_share_an_id_and_run_out_with_a_clear_error(namespace):
    held = [ros_domains.reserve(namespace=namespace) for _ in ros_domains.DOMAIN_IDS]
    try:
        ids = [r.domain_id for r in held]
        assert sorted(ids) == sorted(ros_domains.DOMAIN_IDS)      # each one once
        assert 0 not in ids and max(ids) <= 101
        with pytest.raises(ros_domains.DomainsExhausted, match=namespace):
            ros_domains.reserve(namespace=namespace)
    finally:
        for reservation in held:
            reservation.release()


def test_a_released_id_can_be_reserved_again(namespace):
    with ros_domains.reserve([7], namespace) as first:
        assert first.domain_id == 7 and first.held
        with pytest.raises(ros_domains.DomainsExhausted):
            ros_domains.reserve([7], namespace)
    assert not first.held
    again = ros_domains.reserve([7], namespace)
    assert again.domain_id == 7
    again.release()
    again.release()                               # a second release does nothing
    ros_domains.reserve([7], namespace).release()


def test_a_reservation_excludes_other_processes_until_its_holder_exits(namespace):
    child, answer = start_holder(namespace, 5)
    try:
        assert answer == '5'
        with pytest.raises(ros_domains.DomainsExhausted):
            ros_domains.reserve([5], namespace)
        with ros_domains.reserve([5, 6], namespace) as other:
            assert other.domain_id == 6
    finally:
        child.kill()                              # no clean-up code runs: the kernel frees it
        child.wait()
    ros_domains.reserve([5], namespace).release()

    with ros_domains.reserve([5], namespace):
        child, answer = start_holder(namespace, 5)
        assert answer == 'exhausted' and child.wait() == 3


def test_subprocesses_do_not_inherit_the_reservation(namespace):
    reservation = ros_domains.reserve([9], namespace)
    child = subprocess.Popen([sys.executable, '-c', 'import sys; sys.stdin.read()'],
                             stdin=subprocess.PIPE)
    try:
        reservation.release()
        ros_domains.reserve([9], namespace).release()   # the child does not hold it
    finally:
        child.communicate('')


def test_fixture_ids_are_held_distinct_and_apart_from_the_session_default(
        domain_id, process_domain_id):
    session_id = int(os.environ['ROS_DOMAIN_ID'])
    assert len({domain_id, process_domain_id, session_id}) == 3
    for held in (domain_id, process_domain_id, session_id):
        assert held in ros_domains.DOMAIN_IDS
        probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        with pytest.raises(OSError, match='Address already in use'):
            probe.bind(ros_domains.socket_name(held))
        probe.close()


def test_home_ros_home_and_rcl_logs_are_temporary(private_home, session_home, domain_id):
    assert os.environ['HOME'] == str(private_home)
    assert os.environ['ROS_HOME'] == str(private_home / '.ros')
    log_dir = session_home / '.ros' / 'log'
    assert os.environ['ROS_LOG_DIR'] == str(log_dir)
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id)
    try:
        node = rclpy.create_node('isolation_probe', context=context)
        node.get_logger().info('a line for the log file')
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=context)
    # rcl opens one log file per process, at its first init: this process's is here.
    assert list(log_dir.glob(f'python_{os.getpid()}_*.log'))


def test_changes_to_the_users_files_are_named(tmp_path):
    home = tmp_path / 'user'
    (home / '.ros' / 'quatcal').mkdir(parents=True)
    journal = home / '.ros' / 'quatcal' / 'samples.csv'
    journal.write_text('# header\n')
    dirs = user_files.watched_dirs({'HOME': str(home)})
    assert home / '.ros' / 'log' in dirs and home / '.ros' / 'quatcal' in dirs
    before = user_files.snapshot(dirs)
    assert user_files.changes(before, user_files.snapshot(dirs)) == []

    journal.rename(journal.with_name('samples.previous-1.csv'))
    (home / '.ros' / 'log').mkdir()
    (home / '.ros' / 'log' / 'python_1_2.log').write_text('x')
    changed = '\n'.join(user_files.changes(before, user_files.snapshot(dirs)))
    assert f'{journal}: removed' in changed
    assert f'{journal.with_name("samples.previous-1.csv")}: created' in changed
    assert f'{home / ".ros" / "log"}: created' in changed


def test_a_changed_file_of_the_same_size_is_named(tmp_path):
    home = tmp_path / 'user'
    result = home / '.ros' / 'quatcal' / 'calibration.yaml'
    result.parent.mkdir(parents=True)
    result.write_text('a')
    dirs = user_files.watched_dirs({'HOME': str(home), 'ROS_LOG_DIR': str(tmp_path / 'logs')})
    assert tmp_path / 'logs' in dirs
    before = user_files.snapshot(dirs)
    result.write_text('b')
    os.utime(result, ns=(1, 1))
    assert user_files.changes(before, user_files.snapshot(dirs)) == [
        f'{result}: modified (same size, new mtime)']


def test_a_file_created_and_removed_in_a_watched_directory_is_named(tmp_path):
    """Only the directory's mtime tells: a temporary file that a run wrote and then removed."""
    home = tmp_path / 'user'
    journal_dir = home / '.ros' / 'quatcal'
    journal_dir.mkdir(parents=True)
    os.utime(journal_dir, ns=(1, 1))
    dirs = user_files.watched_dirs({'HOME': str(home)})
    before = user_files.snapshot(dirs)
    (journal_dir / 'samples.csv.tmp').write_text('x')
    (journal_dir / 'samples.csv.tmp').unlink()
    assert user_files.changes_of(before, user_files.snapshot(dirs), {os.getpid()}) == (
        [f'{journal_dir}: modified (an entry created and removed since)'], [])


def test_rcl_logs_of_other_processes_are_told_apart(tmp_path):
    """A ROS system running beside the tests writes its rcl logs: not the session's doing."""
    home = tmp_path / 'user'
    log_dir = home / '.ros' / 'log'
    log_dir.mkdir(parents=True)
    dirs = user_files.watched_dirs({'HOME': str(home)})
    before = user_files.snapshot(dirs)
    (log_dir / 'python_4242_1796456042944.log').write_text('another node')
    assert user_files.changes_of(before, user_files.snapshot(dirs), {os.getpid()}) == (
        [], [f'{log_dir / "python_4242_1796456042944.log"}: created'])
    ours = log_dir / f'python_{os.getpid()}_1796456042945.log'
    ours.write_text('a test')
    (home / '.ros' / 'quatcal').mkdir()
    changed, others = user_files.changes_of(before, user_files.snapshot(dirs), {os.getpid()})
    assert f'{ours}: created' in changed
    assert f'{home / ".ros" / "quatcal"}: created (now holds [])' in changed
    assert others == [f'{log_dir / "python_4242_1796456042944.log"}: created']


def test_the_session_knows_the_processes_it_starts(pytestconfig):
    from conftest import SESSION
    process = subprocess.run([sys.executable, '-c', 'import os; print(os.getpid())'],
                             capture_output=True, text=True, check=True)
    assert int(process.stdout) in pytestconfig.stash[SESSION]['pids']
