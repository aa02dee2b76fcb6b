"""launch/calibrate.launch.py: valid Python naming real settings (launch is not installed here)."""

import ast
from pathlib import Path
import py_compile

from quatcal_ros.stream.settings import SETTINGS, TF_FRAMES

LAUNCH = Path(__file__).resolve().parents[1] / 'launch' / 'calibrate.launch.py'


def test_the_launch_file_compiles_and_declares_the_frames_setup_and_params_file(tmp_path):
    py_compile.compile(str(LAUNCH), cfile=str(tmp_path / 'launch.pyc'), doraise=True)
    tree = ast.parse(LAUNCH.read_text())
    frames = next(node.value for node in ast.walk(tree) if isinstance(node, ast.Assign)
                  and any(getattr(t, 'id', None) == 'FRAMES' for t in node.targets))
    names = [element.elts[0].value for element in frames.elts]
    assert tuple(names) == TF_FRAMES
    declared = {node.args[0].value for node in ast.walk(tree) if isinstance(node, ast.Call)
                and getattr(node.func, 'id', None) == 'DeclareLaunchArgument'
                and node.args and isinstance(node.args[0], ast.Constant)}
    assert declared == {'setup', 'params_file'}   # and the FRAMES, by name above
    # Every parameter the launch file sets is a setting of the node.
    keys = {key.value for node in ast.walk(tree) if isinstance(node, ast.Dict)
            for key in node.keys if isinstance(key, ast.Constant)}
    assert keys <= {setting.name for setting in SETTINGS}
    assert {'setup', 'link_frame', 'sensor_frame'} <= keys
