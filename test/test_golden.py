"""
The estimator's answers on recorded cases stay what they were (golden_answers.py).

Synthetic cells of every noise mode, both setups, the options that branch the pipeline, the
reduced-DOF paths, both shared real recordings (configured rightly and wrongly), a live
calibrator's warm solves sample by sample, and inputs that must be refused: decisions
exactly, estimates within 0.02 of their sigma. A deliberate change of the answers is recorded
again with test/golden/record.py, and its commit says what moved.
"""

from golden_answers import differences, load, solve
import pytest

CASES = load()


@pytest.mark.parametrize('name, samples, options, live, answer', CASES,
                         ids=[case[0] for case in CASES])
def test_the_answer_is_the_recorded_one(name, samples, options, live, answer):
    found = differences(answer, solve(samples, options, live))
    assert not found, f'{name}: ' + '; '.join(found)


def test_the_comparison_sees_a_moved_answer_and_a_changed_decision():
    answer = next(case[4] for case in CASES if case[0] == 'bad-25% eye_in_hand 20')
    assert answer['rejected'], 'the case should have rejected samples'

    def moved_along_x(sigmas):   # the translation moved by `sigmas` of its uncertainty
        x, y, z = answer['translation']
        return dict(answer, translation=[x + 1e-3 * sigmas * answer[
            'translation_uncertainty_mm'], y, z])
    assert any('translation moved' in d for d in differences(answer, moved_along_x(0.05)))
    assert not differences(answer, moved_along_x(0.01))
    changed = dict(answer, rejected=answer['rejected'][1:])
    assert any(d.startswith('rejected') for d in differences(answer, changed))
    assert not differences(answer, dict(answer, uncertainty_deg=answer['uncertainty_deg'] * 1.01))
    assert differences(answer, dict(answer, uncertainty_deg=answer['uncertainty_deg'] * 1.05))
