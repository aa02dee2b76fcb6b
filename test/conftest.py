"""Fixtures and settings shared by all tests of quatcal_ros."""

import os
from pathlib import Path

import numpy as np
import pytest
from quatcal_ros.core.pose import Pose
from quatcal_ros.core.quaternion import wxyz_from_xyzw

REPO_ROOT = Path(__file__).resolve().parents[1]

# Nodes started by the tests (in-process or as subprocesses, which inherit this) talk over real
# DDS: keep discovery on this machine so parallel runs and other hosts do not interfere.
os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')


@pytest.fixture(autouse=True)
def private_home(tmp_path_factory, monkeypatch):
    """
    Give every test (and the processes it starts) a HOME of its own.

    The calibrator node writes ~/.ros/quatcal/samples.csv (its samples journal) by default and
    moves an earlier one aside: tests must not touch the user's files.  Returns the directory.
    """
    home = tmp_path_factory.mktemp('home')
    monkeypatch.setenv('HOME', str(home))
    return home


@pytest.fixture(scope='session')
def repo_root():
    """Return the repository root (the package directory), as a pathlib.Path."""
    return REPO_ROOT


@pytest.fixture(scope='session')
def shared_dir():
    """
    Return the project's shared/ directory (datasets/, paper/), as a pathlib.Path.

    Found through the environment variable QUATCAL_SHARED, else at ../shared beside the
    repository (where CI puts it). Tests that use it are skipped when it is missing.
    """
    env = os.environ.get('QUATCAL_SHARED')
    candidate = Path(env) if env else REPO_ROOT.parent / 'shared'
    if not (candidate / 'datasets').is_dir():
        how = 'QUATCAL_SHARED=%s' % env if env else 'default ../shared beside the repository'
        pytest.skip('shared data not found: %s has no datasets/ (%s); set QUATCAL_SHARED to '
                    'the shared/ directory to run this test' % (candidate, how))
    return candidate.resolve()


@pytest.fixture(scope='session')
def eth_streams(shared_dir):
    """
    Return the ETH robot-arm recording as (link, camera) lists of (stamp_ns, Pose).

    Link: sr300_hinge in base_link, ~50 Hz. Camera: the IR camera in the target frame, ~30 Hz
    (SOURCE.md: the inverse of T_sensor_obj, so solve it with invert_sensor).
    """
    folder = shared_dir / 'datasets' / 'ethz_robot_arm_real'

    def load(name):
        rows = np.loadtxt(folder / name, delimiter=',')
        stamps = np.rint(rows[:, 0] * 1e9).astype(np.int64)
        return [(int(s), Pose(r[1:4], wxyz_from_xyzw(r[4:8]))) for s, r in zip(stamps, rows)]
    return load('link_hinge_in_base.csv'), load('ir_camera_in_target.csv')
