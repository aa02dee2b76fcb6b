"""package.xml declares every third-party import of the package with its rosdep key."""

from pathlib import Path
import sys
import xml.etree.ElementTree as ElementTree

from test_layers import imports, modules

ROOT = Path(__file__).resolve().parents[1]
# Python packages whose rosdep key is not their import name; ROS packages are their own key.
ROSDEP_KEYS = {'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'yaml': 'python3-yaml',
               'rosbags': 'python3-rosbags-pip', 'cv2': 'python3-opencv',
               'matplotlib': 'python3-matplotlib'}


def declared(kind):
    """Return the keys of package.xml's <kind> elements."""
    root = ElementTree.parse(ROOT / 'package.xml').getroot()
    return {element.text.strip() for element in root.iter(kind)}


def test_every_import_has_an_exec_depend():
    needed = {}
    for _, name, path in modules():
        for imported in imports(path):
            top = imported.split('.')[0]
            if top not in sys.stdlib_module_names and top != 'quatcal_ros':
                needed.setdefault(ROSDEP_KEYS.get(top, top), name)
    missing = {key: where for key, where in needed.items() if key not in declared('exec_depend')}
    assert not missing, f'package.xml lacks <exec_depend> for {missing} (key: first importer)'


def test_the_test_tools_are_test_depends():
    assert {'ament_flake8', 'ament_pep257', 'python3-pytest'} <= declared('test_depend')
