"""
The package's rooms and who may import whom: the tree is the architecture.

Every module of quatcal_ros is read (its source, with ast: imports inside functions count too)
and checked against LAYERS: the subpackages of quatcal_ros it may import, and the third-party
packages it may import.  The standard library is always allowed.  A second check imports each
module below the ROS layer in a fresh interpreter and looks at sys.modules, so a module that
pulls rclpy in through another path is caught too.
"""

import ast
from pathlib import Path
import subprocess
import sys

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / 'quatcal_ros'
ROS_MESSAGES = {'builtin_interfaces', 'diagnostic_msgs', 'geometry_msgs', 'rcl_interfaces',
                'rosgraph_msgs', 'sensor_msgs', 'std_msgs', 'std_srvs', 'tf2_msgs',
                'visualization_msgs'}
ROS = {'rclpy', 'tf2_ros'} | ROS_MESSAGES
# room: (rooms of quatcal_ros it may import, third-party packages it may import)
LAYERS = {
    'core': ({'core'}, {'numpy'}),
    'sim': ({'core', 'sim'}, {'numpy'}),
    'stream': ({'core', 'stream'}, {'numpy'}),
    'files': ({'core', 'files'}, {'numpy', 'yaml'}),
    'ros': ({'core', 'stream', 'files', 'sim', 'vision', 'ros'},
            {'numpy', 'yaml', 'rosbags', 'cv2'} | ROS),
    'vision': ({'core', 'files', 'vision'}, {'numpy', 'cv2'}),
    'report': ({'core', 'files', 'report'}, {'numpy', 'matplotlib'}),
    'tools': ({'core', 'stream', 'files', 'sim', 'ros', 'vision', 'report', 'tools'},
              {'numpy', 'yaml'} | ROS),
    # quatcal_ros/__main__.py (imports its tools by name; ros.stop_signals first for the
    # nodes; files.text_input's typo check for a tool's name) and solver.py (the contract's)
    '': ({'core', 'files', 'ros'}, set()),
}


def modules():
    """Return every module of the package as (room, dotted name, path)."""
    found = []
    for path in sorted(PACKAGE.rglob('*.py')):
        parts = path.relative_to(PACKAGE).with_suffix('').parts
        room = parts[0] if len(parts) > 1 else ''
        found.append((room, '.'.join(('quatcal_ros',) + parts), path))
    return found


def imports(path):
    """Return the (dotted) names `path` imports, at any depth of its source."""
    names = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            if node.module == 'quatcal_ros':
                names += [f'quatcal_ros.{alias.name}' for alias in node.names]
            else:
                names.append(node.module)
    return names


def test_every_room_is_known():
    rooms = {p.name for p in PACKAGE.iterdir() if (p / '__init__.py').is_file()}
    assert rooms == set(LAYERS) - {''}


@pytest.mark.parametrize('room, name, path', modules(), ids=lambda v: str(v))
def test_module_imports_only_what_its_room_may(room, name, path):
    rooms, third_party = LAYERS[room]
    wrong = []
    for imported in imports(path):
        parts = imported.split('.')
        if parts[0] == 'quatcal_ros':
            if len(parts) < 2 or parts[1] not in rooms:
                wrong.append(imported)
        elif parts[0] not in sys.stdlib_module_names and parts[0] not in third_party:
            wrong.append(imported)
    assert not wrong, f'{name} (room {room or "top"!r}) imports {wrong}'


def test_main_names_only_tools_that_exist():
    from quatcal_ros.__main__ import TOOLS
    for module, function, _ in TOOLS.values():
        assert (PACKAGE.parent / (module.replace('.', '/') + '.py')).is_file(), module


BELOW_ROS = [name for room, name, _ in modules() if room in ('core', 'sim', 'stream', 'files')]


def test_modules_below_ros_load_no_ros_or_rosbags(repo_root):
    code = ('import importlib, sys\n'
            f'for name in {BELOW_ROS!r}:\n'
            '    importlib.import_module(name)\n'
            f'bad = sorted(m for m in sys.modules if m.split(".")[0] in {sorted(ROS)!r} + '
            '["rosbags", "cv2"])\n'
            'sys.exit(str(bad) if bad else 0)\n')
    subprocess.run([sys.executable, '-c', code], check=True, cwd=repo_root)


def test_core_and_stream_load_no_yaml(repo_root):
    names = [name for room, name, _ in modules() if room in ('core', 'sim', 'stream')]
    code = ('import importlib, sys\n'
            f'for name in {names!r}:\n'
            '    importlib.import_module(name)\n'
            'sys.exit("yaml loaded" if "yaml" in sys.modules else 0)\n')
    subprocess.run([sys.executable, '-c', code], check=True, cwd=repo_root)


def test_solve_of_a_csv_loads_no_ros_yaml_or_bag_reader(repo_root, tmp_path):
    """`solve FILE.csv` imports what it needs and no more (its start-up is a user's wait)."""
    from quatcal_ros.files.samples_csv import format_samples
    from quatcal_ros.sim import simulation
    import numpy as np
    rng = np.random.default_rng(2)
    cell = simulation.random_cell(rng)
    path = tmp_path / 'samples.csv'
    path.write_text(format_samples(simulation.samples(rng, cell, 8, rotation_noise_deg=0.2)[0]))
    code = ('import runpy, sys\n'
            f'sys.argv = ["quatcal_ros", "solve", {str(path)!r}]\n'
            'try:\n'
            '    runpy.run_module("quatcal_ros", run_name="__main__")\n'
            'except SystemExit as stop:\n'
            '    assert not stop.code, stop.code\n'
            'loaded = [m for m in ("rclpy", "rosbags", "yaml", "scipy", "cv2", "matplotlib",\n'
            '                      "xml.sax", "urllib.request") if m in sys.modules]\n'
            'sys.exit(f"loaded {loaded}" if loaded else 0)\n')
    done = subprocess.run([sys.executable, '-c', code], cwd=repo_root, capture_output=True,
                          text=True)
    assert done.returncode == 0, done.stderr[-2000:]
    assert '"rotation"' in done.stdout
