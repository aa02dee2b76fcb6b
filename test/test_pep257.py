"""ament_pep257 (pydocstyle with ROS 2's ignore list) over the package."""

from pathlib import Path

from ament_pep257.main import main
import pytest

ROOT = Path(__file__).resolve().parents[1]
CHECKED = [str(ROOT / p) for p in ('setup.py', 'quatcal_ros', 'test', 'bench', 'launch')
           if (ROOT / p).exists()]


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257():
    rc = main(argv=CHECKED)
    assert rc == 0, 'Found code style errors / warnings'
