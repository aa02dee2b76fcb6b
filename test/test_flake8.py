"""ament_flake8 over the package, as in the ROS 2 packages' own test suites."""

from pathlib import Path

from ament_flake8.main import main_with_errors
import pytest

ROOT = Path(__file__).resolve().parents[1]
# Listed explicitly (not the whole directory) so colcon's build/, install/ and log/ at the repo
# root are never linted; missing ones are left out.
CHECKED = [str(ROOT / p) for p in ('setup.py', 'quatcal_ros', 'test', 'bench', 'launch')
           if (ROOT / p).exists()]


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8():
    rc, errors = main_with_errors(argv=CHECKED)
    assert rc == 0, \
        'Found %d code style errors / warnings:\n' % len(errors) + \
        '\n'.join(errors)
