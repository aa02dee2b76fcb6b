"""
Build quatcal_ros with colcon and run the installed calibrator the way `ros2 run` does.

ros2cli is not installable here, so the test does what `ros2 run quatcal_ros calibrator` does:
ament_index_python.packages.get_package_prefix() over AMENT_PREFIX_PATH, then
<prefix>/lib/quatcal_ros/calibrator, started with the installed site-packages on PYTHONPATH.
"""

import os
from pathlib import Path
import shutil
import signal
import subprocess
import sys
import threading
import time

from ament_index_python.packages import get_package_prefix
import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = 'quatcal_ros'
TOOLS = ('calibrator', 'sim_cell', 'solve', 'replay')
PY = 'python%d.%d' % sys.version_info[:2]


def _colcon():
    here = Path(sys.executable).parent / 'colcon'  # the venv's colcon, beside its python
    found = str(here) if here.exists() else shutil.which('colcon')
    if not found:
        pytest.fail('colcon is not installed: run scripts/bootstrap.sh (requirements/dev.txt)')
    return found


@pytest.fixture(scope='module')
def workspace(tmp_path_factory):
    """Build the repository with colcon in a temporary workspace; return its install base."""
    ws = tmp_path_factory.mktemp('colcon_ws')
    env = dict(os.environ, COLCON_HOME=str(ws / 'colcon_home'))  # no user defaults
    cmd = [_colcon(), '--log-base', str(ws / 'log'), 'build',
           '--base-paths', str(ROOT),
           '--build-base', str(ws / 'build'), '--install-base', str(ws / 'install'),
           '--event-handlers', 'console_direct+']
    proc = subprocess.run(cmd, cwd=ws, env=env, stdin=subprocess.DEVNULL,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                          timeout=600)
    assert proc.returncode == 0, 'colcon build failed:\n' + proc.stdout
    built = sorted(p.name for p in (ws / 'build').iterdir() if p.is_dir())
    assert built == [PKG], 'colcon should find only this package (COLCON_IGNORE?): %s' % built
    return ws / 'install'


@pytest.mark.colcon
def test_installed_layout(workspace):
    prefix = workspace / PKG
    for tool in TOOLS:
        exe = prefix / 'lib' / PKG / tool
        assert exe.is_file(), '%s missing: check setup.cfg install_scripts' % exe
        assert os.access(exe, os.X_OK), '%s is not executable' % exe
    marker = prefix / 'share' / 'ament_index' / 'resource_index' / 'packages' / PKG
    assert marker.is_file(), 'ament index marker missing: ros2 run cannot find the package'
    assert (prefix / 'share' / PKG / 'package.xml').is_file()
    site = prefix / 'lib' / PY / 'site-packages'
    assert (site / PKG).is_dir(), 'Python package not installed under %s' % site
    for config in sorted((ROOT / 'config').glob('*.yaml')):
        assert (prefix / 'share' / PKG / 'config' / config.name).is_file()
    assert (prefix / 'share' / PKG / 'launch' / 'calibrate.launch.py').is_file()


def _run_env(prefix, domain_id):
    env = dict(os.environ)
    env['AMENT_PREFIX_PATH'] = os.pathsep.join(
        [str(prefix)] + [p for p in env.get('AMENT_PREFIX_PATH', '').split(os.pathsep) if p])
    env['PYTHONPATH'] = os.pathsep.join(
        [str(prefix / 'lib' / PY / 'site-packages')]
        + [p for p in env.get('PYTHONPATH', '').split(os.pathsep) if p])
    env['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
    env['ROS_DOMAIN_ID'] = str(domain_id)
    env['PYTHONUNBUFFERED'] = '1'
    return env


def _wait_for_node(name, domain_id, proc, timeout):
    """Return True once a node called `name` shows in the ROS graph of domain_id."""
    import rclpy
    from rclpy.signals import SignalHandlerOptions

    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain_id,
               signal_handler_options=SignalHandlerOptions.NO)
    try:
        probe = rclpy.create_node('quatcal_test_probe', context=context)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and proc.poll() is None:
            if name in [n for n, _ in probe.get_node_names_and_namespaces()]:
                return True
            time.sleep(0.1)
        return False
    finally:
        context.try_shutdown()


@pytest.mark.colcon
def test_ros2_run_calibrator_starts_and_stops_on_sigint(workspace, monkeypatch, domain_id):
    monkeypatch.setenv('AMENT_PREFIX_PATH', str(workspace / PKG))
    prefix = Path(get_package_prefix(PKG))  # what `ros2 run` asks first
    assert prefix == workspace / PKG
    exe = prefix / 'lib' / PKG / 'calibrator'

    proc = subprocess.Popen([str(exe)], env=_run_env(prefix, domain_id), cwd=workspace,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines = []
    reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
    reader.start()
    try:
        running = _wait_for_node('calibrator', domain_id, proc, timeout=30.0)
        time.sleep(0.5)  # from constructing the node to spinning
        assert proc.poll() is None, \
            'calibrator exited early (code %s):\n%s' % (proc.returncode, ''.join(lines))
        assert running, 'no node "calibrator" in the graph after 30 s:\n' + ''.join(lines)
        proc.send_signal(signal.SIGINT)
        code = proc.wait(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        reader.join(timeout=5)
    output = ''.join(lines)
    assert code == 0, 'calibrator exited with %s after SIGINT:\n%s' % (code, output)
    assert 'Traceback' not in output, output


@pytest.mark.colcon
def test_installed_copy_is_imported(workspace, domain_id):
    """The installed tools import the installed package, not the working tree."""
    prefix = workspace / PKG
    code = 'import quatcal_ros.ros.node as m; print(m.__file__)'
    # cwd outside the repo: `python -c` puts the cwd first on sys.path.
    proc = subprocess.run([sys.executable, '-c', code], env=_run_env(prefix, domain_id),
                          cwd=workspace, stdin=subprocess.DEVNULL, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert Path(proc.stdout.strip()).is_relative_to(prefix), proc.stdout
