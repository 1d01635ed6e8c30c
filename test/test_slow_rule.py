"""test/conftest.py's rule for the slow mark: a parametrized test keeps a case in `make test`."""
from __future__ import annotations

from pathlib import Path

pytest_plugins = ['pytester']

CASES = '''
import pytest

@pytest.mark.parametrize('n', [pytest.param(1, marks=pytest.mark.slow),
                               pytest.param(2, marks=pytest.mark.slow)])
def test_every_case_slow(n):
    pass

@pytest.mark.parametrize('n', [1, pytest.param(2, marks=pytest.mark.slow)])
def test_first_case_kept(n):
    pass

@pytest.mark.slow
@pytest.mark.parametrize('n', [1, 2])
def test_slow_whole(n):
    pass
'''


def test_a_test_whose_every_case_is_slow_fails_make_test_and_the_others_do_not(pytester):
    pytester.makeconftest((Path(__file__).parent / 'conftest.py').read_text())
    pytester.makeini('[pytest]\nmarkers =\n    slow: left out of make test\n')
    pytester.makepyfile(test_cases=CASES)
    result = pytester.runpytest('-m', 'not slow')
    result.assert_outcomes(passed=1, failed=1, deselected=5)
    result.stdout.fnmatch_lines(['*every case of test_every_case_slow is marked slow*'])
    assert 'test_first_case_kept is marked' not in result.stdout.str()
    assert 'test_slow_whole is marked' not in result.stdout.str()
    # make test-slow runs the slow cases alone (the unmarked case and the rule's item are left)
    pytester.runpytest('-m', 'slow').assert_outcomes(passed=5, deselected=2)
