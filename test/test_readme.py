"""
The README against the code: every name a user looks up there must exist there.

Read from the code and looked up in README.md: every setting of the settings table, every
option of `solve` and `replay`, the topics and services of the nodes, the /diagnostics keys,
the bad-message reasons, and the keys of the JSON output and of the result file.  The user
documents must not point at things a user cannot follow (issue numbers, design contracts), and
the first code block of README.md starts with the two set-up commands.
"""

import ast
import json
import os
from pathlib import Path
import re
import subprocess
import sys

import pytest
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.files import importers
from quatcal_ros.files.persistence import result_document
from quatcal_ros.stream.message_checks import REASONS, STREAMS
from quatcal_ros.stream.settings import SETTINGS
from quatcal_ros.tools.cli import replay_parser, solve_main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / 'README.md'
USER_DOCUMENTS = (README, ROOT / 'bench' / 'README.md')
PACKAGE = ROOT / 'quatcal_ros'
NODE_SOURCES = (PACKAGE / 'ros' / 'node.py', PACKAGE / 'ros' / 'sim_cell.py')
DIAGNOSTICS_SOURCE = PACKAGE / 'ros' / 'diagnostics.py'
MOVEIT_SAMPLES = ROOT / 'data' / 'moveit_pose_samples' / 'pose_samples.json'
# The calibrator's interface as the README presents it; each must still exist in the code.
NODE_INTERFACE = ('~/rotation', '~/transform', '~/capture', '~/reset', '~/save', '/diagnostics',
                  'link_pose', 'sensor_pose')
ENDPOINT_CALLS = ('create_publisher', 'create_subscription', 'create_service', 'create_client')
OPTION = re.compile(r'(?<![\w-])--[a-z][a-z0-9-]*')


@pytest.fixture(scope='module')
def readme():
    """Return the text of README.md."""
    return README.read_text(encoding='utf-8')


def quoted(name, text):
    """Tell whether `name` appears in `text` as code (`name`)."""
    return f'`{name}`' in text


def options_in(help_text):
    """Return the set of long options named in an argparse help text, --help left out."""
    return set(OPTION.findall(help_text)) - {'--help'}


def mentions_option(option, text):
    """Tell whether `option` appears in `text` as a whole word (not as part of a longer one)."""
    return re.search(rf'(?<![\w-]){re.escape(option)}(?![\w-])', text) is not None


def endpoint_names(path):
    """Return the literal topic and service names that `path` creates publishers etc. for."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding='utf-8'), str(path))):
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in ENDPOINT_CALLS and len(node.args) >= 2
                and isinstance(node.args[1], ast.Constant)
                and isinstance(node.args[1].value, str)):
            names.add(node.args[1].value)
    return names


def diagnostic_keys():
    """Return the keys of the `values` dict that diagnostics.calibrator_status publishes."""
    tree = ast.parse(DIAGNOSTICS_SOURCE.read_text(encoding='utf-8'), str(DIAGNOSTICS_SOURCE))
    for node in ast.walk(tree):
        if (isinstance(node, ast.Assign) and isinstance(node.value, ast.Dict)
                and any(isinstance(t, ast.Name) and t.id == 'values' for t in node.targets)):
            return {key.value for key in node.value.keys if isinstance(key, ast.Constant)}
    raise AssertionError(f'no `values = {{...}}` in {DIAGNOSTICS_SOURCE}')


def test_every_setting_is_in_the_readme(readme):
    missing = [setting.name for setting in SETTINGS if not quoted(setting.name, readme)]
    assert not missing, f'settings missing from README.md: {missing}'


def test_every_option_of_solve_and_replay_is_in_the_readme(readme):
    solve_help = subprocess.run(
        [sys.executable, '-m', 'quatcal_ros', 'solve', '--help'], cwd=ROOT, text=True,
        capture_output=True, timeout=120,
        env=dict(os.environ, PYTHONPATH=os.pathsep.join(
            [str(ROOT)] + [p for p in [os.environ.get('PYTHONPATH')] if p])))
    assert solve_help.returncode == 0, solve_help.stderr
    tools = {'solve': options_in(solve_help.stdout),
             'replay': options_in(replay_parser().format_help())}
    assert {'--setup', '--method'} <= tools['solve'] & tools['replay'], tools
    missing = {tool: sorted(o for o in options if not mentions_option(o, readme))
               for tool, options in tools.items()}
    assert not any(missing.values()), f'options missing from README.md: {missing}'


def test_every_topic_and_service_of_the_nodes_is_in_the_readme(readme):
    in_code = set(STREAMS).union(*(endpoint_names(path) for path in NODE_SOURCES))
    gone = sorted(set(NODE_INTERFACE) - in_code)
    assert not gone, f'README interface names no longer in the node code: {gone}'
    missing = sorted(name for name in set(NODE_INTERFACE) | in_code if not quoted(name, readme))
    assert not missing, f'topics and services missing from README.md: {missing}'


def test_every_diagnostics_key_and_bad_message_reason_is_in_the_readme(readme):
    keys = diagnostic_keys()
    assert {'state', 'samples', 'stale'} <= keys, keys
    missing = sorted(name for name in keys | set(REASONS) if not quoted(name, readme))
    assert not missing, f'/diagnostics keys or bad-message reasons missing: {missing}'


def test_the_keys_of_the_json_and_the_result_file_are_in_the_readme(readme, capsys):
    assert solve_main([str(MOVEIT_SAMPLES), '--setup', 'eye_to_hand']) == 0
    printed = json.loads(capsys.readouterr().out)
    missing = sorted(key for key in printed if not quoted(key, readme))
    assert not missing, f'JSON keys missing from README.md: {missing}'
    samples = importers.load_samples(str(MOVEIT_SAMPLES), 'auto', 'eye_to_hand').samples
    result = calibrate(samples, CalibrationOptions(setup='eye_to_hand'))
    document = result_document(result, 'base_link', 'camera', 'eye_to_hand')
    missing = sorted(key for key in document
                     if not re.search(rf'^\s*{re.escape(key)}:', readme, re.MULTILINE))
    assert not missing, f'result file keys missing from the README example: {missing}'


@pytest.mark.parametrize('document', USER_DOCUMENTS, ids=lambda path: path.parent.name)
def test_no_internal_references(document):
    text = document.read_text(encoding='utf-8')
    for pattern in (r'\bissue\s+#?\d', r'\bcontract\s+\d', r'DESIGN\.md'):
        found = re.search(pattern, text, re.IGNORECASE)
        assert found is None, f'{document.name}: {found.group(0)!r} cannot be looked up by users'


def test_the_first_code_block_starts_with_make_demo_and_make_test(readme):
    block = re.search(r'^```[^\n]*\n(.*?)^```', readme, re.MULTILINE | re.DOTALL)
    assert block is not None, 'README.md has no code block'
    commands = [line.split('#', 1)[0].strip() for line in block.group(1).splitlines()]
    assert [c for c in commands if c][:2] == ['make demo', 'make test'], block.group(1)


def test_the_module_map_names_every_module():
    package = Path(__file__).resolve().parents[1] / 'quatcal_ros'
    text = (Path(__file__).resolve().parents[1] / 'README.md').read_text()
    missing = [str(path.relative_to(package)) for path in sorted(package.glob('*/*.py'))
               if path.name != '__init__.py' and f'`{path.name}`' not in text]
    assert not missing, f'README.md module map lacks {missing}'
