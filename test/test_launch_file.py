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
    # The result's frames follow the TF frames of the setup (a runtime setup change too).
    assert 'setup' in keys and not {'link_frame', 'sensor_frame'} & keys


def test_with_tf_frames_the_setup_can_change_at_runtime():
    """The launch file set link_frame to the effector: eye_to_hand was then refused."""
    from quatcal_ros.stream.settings import DEFAULTS, Settings
    frames = dict(zip(TF_FRAMES, ('base_link', 'flange', 'camera', 'marker')))
    config = Settings.from_values(dict(DEFAULTS, **frames))
    assert config.result_frames == ('flange', 'camera')
    assert config.updated(setup='eye_to_hand').result_frames == ('base_link', 'camera')
