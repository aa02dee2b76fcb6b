"""
Record the golden answers (answers.json) that test_golden.py holds the estimator to.

Run it after a deliberate change of the estimator's answers, and say in the commit which
answers moved and why:

    .venv/bin/python test/golden/record.py

Each case stores its samples beside its answer, as samples CSV text at full precision, so
the file does not depend on the simulation or the capture staying as they are. A case whose
answer moves beyond the tolerances (golden_answers.py) when its inputs move by PERTURBATION
(relative and absolute; three draws) sits on an edge that another machine's rounding could
tip: the recorder leaves it out and says so.
"""

from dataclasses import replace
import json
from pathlib import Path
import sys

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
sys.path.insert(0, str(HERE.parents[1] / 'bench'))
from bench_honesty import eth_samples  # noqa: E402,I100
from golden_answers import ANSWERS, differences, solve  # noqa: E402,I100
from golden_answers import stored_options, stored_samples  # noqa: E402,I100
from quatcal_ros.core.calibration import CalibrationOptions, Thresholds  # noqa: E402
from quatcal_ros.core.pose import Pose, Sample  # noqa: E402
from quatcal_ros.files.importers import read_moveit_json_samples  # noqa: E402
from quatcal_ros.sim import simulation  # noqa: E402

DATA = HERE.parents[1] / 'data'
PERTURBATION = 1e-10
PERTURBATIONS = 3   # draws of it per case
NOISE = {
    'isotropic': {'rotation_noise_deg': 0.3, 'translation_noise_m': 0.002},
    'pnp-like': {'sensor_covariance': simulation.pnp_like_covariance()},
    'pnp-like-with-covariances': {'sensor_covariance': simulation.pnp_like_covariance(),
                                  'report_covariance': True},
    'robot-error': {'rotation_noise_deg': 0.3, 'translation_noise_m': 0.002,
                    'link_rotation_noise_deg': 0.1, 'link_translation_noise_m': 0.001},
    'bad-10%': {'rotation_noise_deg': 0.3, 'translation_noise_m': 0.002,
                'outlier_fraction': 0.1},
    'bad-25%': {'rotation_noise_deg': 0.3, 'translation_noise_m': 0.002,
                'outlier_fraction': 0.25},
    'exact': {},
}


def synthetic_cases():
    """Yield (name, samples, options): every noise mode, both setups, options that branch."""
    seed = 0
    for mode, noise in NOISE.items():
        for setup, sizes in (('eye_in_hand', (6, 10, 20)), ('eye_to_hand', (8, 30))):
            for n in sizes:
                seed += 1
                rng = np.random.default_rng(2000 + seed)
                samples = simulation.samples(rng, simulation.random_cell(rng, setup), n,
                                             **noise)[0]
                options = CalibrationOptions(setup=setup)
                yield f'{mode} {setup} {n}', samples, options
                if n == 20:
                    yield from _variants(f'{mode} {setup} {n}', samples, options)
    for kind in ('scara', 'gantry'):
        rng = np.random.default_rng(3000 + len(kind))
        samples = simulation.reduced_dof_samples(rng, simulation.random_cell(rng), 12, kind,
                                                 rotation_noise_deg=0.1,
                                                 translation_noise_m=0.001)
        samples = samples[0] if isinstance(samples, tuple) else samples
        yield f'{kind} 12', samples, CalibrationOptions()
        yield f'{kind} 12 with a known translation', samples, \
            CalibrationOptions(known_translation=(0.01, -0.02, 0.05))


def _variants(name, samples, options):
    yield f'{name} --no-robust', samples, replace(options, robust=False)
    yield f'{name} closed form', samples, replace(options, method='closed-form')
    yield f'{name} consecutive pairs', samples, replace(options, pairs='consecutive')
    yield f'{name} given as inverted', samples, replace(options, invert_sensor=True)
    other = 'eye_to_hand' if options.setup == 'eye_in_hand' else 'eye_in_hand'
    yield f'{name} given as {other}', samples, replace(options, setup=other)
    yield f'{name} strict validation', samples, replace(
        options, validation=Thresholds(max_rotation_deg=0.2, max_translation_mm=1.0))


def real_cases():
    """Yield the two shared recordings (data/), as configured and as misconfigured."""
    arm = eth_samples()   # as `replay --capture continuous` takes them
    inverted = CalibrationOptions(invert_sensor=True)
    yield 'robot arm', arm, inverted
    yield 'robot arm --no-robust', arm, replace(inverted, robust=False)
    yield 'robot arm, every other sample', arm[::2], inverted
    yield 'robot arm given as not inverted', arm, CalibrationOptions()
    cell = read_moveit_json_samples(DATA / 'moveit_pose_samples' / 'pose_samples.json')
    fixed = CalibrationOptions(setup='eye_to_hand')
    yield 'fixed camera', cell, fixed
    yield 'fixed camera --no-robust', cell, replace(fixed, robust=False)
    yield 'fixed camera given as inverted', cell, replace(fixed, invert_sensor=True)


def live_cases():
    """Yield (name, samples, options, sample counts): a live calibrator's warm solves."""
    counts = [6, 13, 14, 17, 20, 23, 29, 31, 38, 45]
    for mode, robust in (('bad-10%', True), ('isotropic', False), ('pnp-like', True)):
        rng = np.random.default_rng(5000 + len(mode))
        samples = simulation.samples(rng, simulation.random_cell(rng), 45, **NOISE[mode])[0]
        yield f'live {mode}{"" if robust else " --no-robust"} 45', samples, \
            CalibrationOptions(robust=robust), counts
    yield 'live robot arm', eth_samples(), CalibrationOptions(invert_sensor=True), \
        [13, 14, 21, 33, 47, 60, 74]


def error_cases():
    """Yield inputs the estimator must refuse, with the error it names."""
    rng = np.random.default_rng(4000)
    samples = simulation.samples(rng, simulation.random_cell(rng), 8,
                                 rotation_noise_deg=0.3, translation_noise_m=0.002)[0]
    yield 'two samples', samples[:2], CalibrationOptions()
    still = [Sample(s.stamp_ns, samples[0].link, samples[0].sensor) for s in samples]
    yield 'the robot never moved', still, CalibrationOptions()


def perturbed(samples, rng):
    """Return stored copies of samples, every pose number moved by PERTURBATION (rel. and abs.)."""
    def moved(values):
        # relative and absolute: a structurally exact 0 (a link that turns about one axis
        # only) moves too, as another machine's rounding could move it
        return (values * (1 + PERTURBATION * rng.standard_normal(len(values)))
                + PERTURBATION * rng.standard_normal(len(values)))

    def pose(p):
        return Pose(moved(p.position), moved(p.quaternion), p.covariance)
    return stored_samples([Sample(s.stamp_ns, pose(s.link), pose(s.sensor)) for s in samples])


def main():
    rng = np.random.default_rng(0)
    sample_sets, cases, left_out = {}, [], []
    single = ((*case, None) for case in (*synthetic_cases(), *real_cases(), *error_cases()))
    for name, samples, options, live in (*single, *live_cases()):
        stored = stored_samples(samples)
        key = next((k for k, v in sample_sets.items() if v == stored), name)
        sample_sets.setdefault(key, stored)
        options = stored_options(options)
        answer = solve(stored, options, live)
        edge = [d for _ in range(PERTURBATIONS)
                for d in differences(answer, solve(perturbed(samples, rng), options, live))]
        if edge:
            left_out.append(name)
            print(f'left out (on an edge): {name}: {edge[0]}')
            continue
        case = {'name': name, 'samples': key, 'options': options, 'answer': answer}
        cases.append(case if live is None else dict(case, live=live))
    used = {case['samples'] for case in cases}
    ANSWERS.write_text(json.dumps(
        {'samples': {k: v for k, v in sample_sets.items() if k in used}, 'cases': cases},
        separators=(',', ':')) + '\n')
    print(f'recorded {len(cases)} cases in {ANSWERS} ({len(left_out)} left out)')


if __name__ == '__main__':
    main()
