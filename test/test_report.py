"""
The --report page of `solve` and `replay`: its content, and a real browser rendering it.

The browser test runs Debian's headless Chromium (.ci/run installs it); where no Chromium is
found it is skipped, saying so. The page must load nothing, run no script, render to a
screenshot that is not blank, and log no console error. With QUATCAL_REPORT_SCREENSHOT=PATH
the test also writes the README's picture there (docs/report.png).
"""

from dataclasses import replace
from html.parser import HTMLParser
import os
from pathlib import Path
import shutil
import subprocess

import cv2
import numpy as np
import pytest
from quatcal_ros.core.calibration import calibrate, CalibrationOptions
from quatcal_ros.report.page import convergence, motion_axes, report_html
from quatcal_ros.sim import simulation
from quatcal_ros.tools.cli import solve_main

REPO = Path(__file__).resolve().parents[1]
MOVEIT_SAMPLES = REPO / 'data' / 'moveit_pose_samples' / 'pose_samples.json'
CHROMIUM = next((path for path in (shutil.which('chromium'), shutil.which('chromium-browser'),
                                   shutil.which('google-chrome')) if path), None)


class Tags(HTMLParser):
    """Every start tag of a page with its attributes."""

    def __init__(self):
        super().__init__()
        self.tags = []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))


def tags_of(text):
    parser = Tags()
    parser.feed(text)
    return parser.tags


@pytest.fixture(scope='module')
def cell():
    rng = np.random.default_rng(11)
    truth = simulation.random_cell(rng)
    samples, _ = simulation.samples(rng, truth, 25, rotation_noise_deg=0.2,
                                    translation_noise_m=0.001, outlier_fraction=0.08)
    options = CalibrationOptions()
    return samples, options, calibrate(samples, options)


def test_the_page_holds_every_part_and_loads_nothing(cell):
    samples, options, result = cell
    page = report_html(result, samples, options, ('tool0', 'camera'), 'cell 11')
    for words in ('Validation:', 'Each sample, predicted from the others',
                  'The estimate as samples were added', 'Coverage of rotation axes',
                  'The mount', 'tool0 &rarr; camera'):
        assert words in page, words
    tags = tags_of(page)
    names = [tag for tag, _ in tags]
    assert names.count('svg') == 4 and 'script' not in names
    # Nothing to fetch: no src, no stylesheet or image link (SVG's xmlns is a name, not a load).
    assert not [attrs for _, attrs in tags if 'src' in attrs or 'href' in attrs
                or 'xlink:href' in attrs and not attrs['xlink:href'].startswith('#')]


def test_frame_names_are_drawn_as_they_are(cell):
    """A $ in a frame name was read as TeX by matplotlib: 'cam$x^$' raised a ParseException."""
    samples, options, result = cell
    page = report_html(result, samples, options, ('tool$0', 'cam$x^$'), 'cell 11')
    assert 'cam$x^$' in page and 'tool$0' in page


def test_image_names_are_written_as_text(cell):
    samples, options, result = cell
    worst = [{**entry, 'image': 'a<b&c.png'} for entry in result.validation['worst']]
    named = replace(result, validation={**result.validation, 'worst': worst})
    page = report_html(named, samples, options, ('tool0', 'camera'))
    assert 'a<b&c.png' not in page and 'a&lt;b&amp;c.png' in page


def test_rejected_and_down_weighted_samples_are_marked(cell):
    samples, _, result = cell
    states = result.sample_states(len(samples))
    assert states.count('rejected') == result.samples - result.inlier_samples > 0
    assert states.count('noisy') == len([n for n in result.noisy
                                         if result.sample_ok[n['sample']]])
    assert {i for i, s in enumerate(states) if s == 'rejected'} == set(
        np.flatnonzero(~np.asarray(result.sample_ok)).tolist())
    # The page says which and why (the figure's rejected bars had no height, no reason).
    page = report_html(result, samples, CalibrationOptions(), ('tool0', 'camera'))
    for entry in [e for e in result.rejected if 'sample' in e]:
        assert f'<li>sample {entry["sample"]} rejected: ' in page
    for entry in result.noisy:
        assert f'<li>sample {entry["sample"]} down-weighted (weight ' in page


def test_the_convergence_ends_at_the_answer_and_the_axes_are_unit(cell):
    samples, options, result = cell
    counts, deg, sigma_deg, mm, sigma_mm = convergence(result, samples, options)
    assert counts[-1] == len(samples) and deg[-1] < 1e-9 and mm[-1] < 1e-9
    assert np.all(np.diff(counts) > 0) and np.all(sigma_deg > 0)
    axes, angles = motion_axes(samples, result, options)
    np.testing.assert_allclose(np.linalg.norm(axes, axis=1), 1.0, atol=1e-12)
    assert len(axes) == result.inlier_samples - 1 and np.all(angles > 0)


def test_solve_writes_the_report_beside_its_json(tmp_path, capsys):
    page = tmp_path / 'report.html'
    assert solve_main([str(MOVEIT_SAMPLES), '--setup', 'eye_to_hand', '--report',
                       str(page)]) == 0
    assert '"rotation"' in capsys.readouterr().out
    text = page.read_text()
    assert 'pose_samples.json' in text and 'class="pass"' in text
    (tmp_path / 'a_file').write_text('')
    assert solve_main([str(MOVEIT_SAMPLES), '--setup', 'eye_to_hand', '--report',
                       str(tmp_path / 'a_file' / 'report.html')]) == 2
    assert 'a_file is a file, not a folder: choose another path' in capsys.readouterr().err


@pytest.mark.skipif(CHROMIUM is None, reason='no Chromium on this machine (apt install '
                                             'chromium; .ci/run installs it)')
def test_chromium_renders_the_page_without_errors(tmp_path, capsys):
    page = tmp_path / 'report.html'
    assert solve_main([str(MOVEIT_SAMPLES), '--setup', 'eye_to_hand', '--report',
                       str(page)]) == 0
    capsys.readouterr()
    shot = tmp_path / 'report.png'
    profile = tmp_path / 'profile'
    env = {**os.environ, 'HOME': str(tmp_path)}
    run = subprocess.run(
        [CHROMIUM, '--headless', '--no-sandbox', '--disable-gpu', '--disable-dev-shm-usage',
         '--no-first-run', f'--user-data-dir={profile}', '--enable-logging=stderr', '--v=0',
         '--window-size=1200,3000', f'--screenshot={shot}', page.as_uri()],
        capture_output=True, text=True, timeout=120, env=env, cwd=tmp_path)
    assert run.returncode == 0, run.stderr[-2000:]
    console = [line for line in run.stderr.splitlines() if 'CONSOLE' in line]
    assert not console, console
    image = cv2.imread(str(shot))
    assert image is not None and image.shape[:2] == (3000, 1200)
    gray = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    # Not blank: text and figures over much of the page, in the figures' colours too.
    rows_with_ink = np.mean((gray < 200).any(axis=1))
    assert rows_with_ink > 0.3, rows_with_ink
    blue = (image[..., 0] > 150) & (image[..., 2] < 120)
    assert blue.sum() > 2000
    target = os.environ.get('QUATCAL_REPORT_SCREENSHOT')   # the README's picture, on request
    if target:   # the top of the page, half size, 32 colours (docs/report.png)
        from PIL import Image
        top = cv2.resize(image[:1800], (600, 900), interpolation=cv2.INTER_AREA)
        Image.fromarray(top[..., ::-1]).quantize(colors=32).save(target, optimize=True)
