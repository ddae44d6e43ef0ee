r"""The options of a method as one record: read from the fields, made from
keywords or the command line's arguments, checked once, and the same
tracker whichever way they come."""
import argparse
import dataclasses

import pytest

from tg_nebp.datasets import Scenario
from tg_nebp.experiments.evaluate import method_tracker
from tg_nebp.experiments.options import (METHOD_OPTIONS, METHODS,
                                         MethodOptions)


def test_the_options_and_who_takes_them_are_the_records_fields():
    # a new option is one field: METHOD_OPTIONS is read from the fields,
    # and every field names methods that exist
    names = [field.name for field in dataclasses.fields(MethodOptions)]
    assert list(METHOD_OPTIONS) == names
    assert METHOD_OPTIONS['lag'] == ('gbp', 'hybrid', 'iekf', 'pcrb')
    assert all(set(takers) <= set(METHODS)
               for takers in METHOD_OPTIONS.values())
    assert MethodOptions().given() == {}
    assert MethodOptions(lag=4, marginal=False).given() == {'lag': 4}


def test_a_record_is_made_from_keywords_or_parsed_arguments():
    options = MethodOptions.of(dict(lag=4, tolerance=0.0))
    assert (options.lag, options.tolerance, options.particles) == (4, 0.0,
                                                                   None)
    parsed = argparse.Namespace(**dict(dataclasses.asdict(options),
                                       method='gbp', seed=3))
    assert MethodOptions.of(parsed) == options
    with pytest.raises(ValueError, match=r"unknown method option\(s\) "
                       r"\['lags'\]"):
        MethodOptions.of(dict(lags=4))


@pytest.mark.parametrize('method,options,match', [
    ('gbp', dict(particles=5), r"'particles' \(--particles\) is for method "
     r"bp or nebp or hybrid, not gbp"),
    ('iekf', dict(incremental=True), "'incremental' is the smoother of the "
     "whole sequence"),
    ('iekf', dict(escape=True, lag=5), r"'escape' \(--escape\) is the full "
     r"smoother's search"),
    ('iekf', dict(escape=True, lag='all', incremental=True),
     "without 'incremental'"),
    ('gbp', dict(lag='all'), r"'lag' 'all' \(the whole sequence\) is for "
     r"method iekf or pcrb"),
    ('iekf', dict(lag=3, marginal=True), "'lag' and 'marginal'"),
    ('bp', dict(iterations=0), "'iterations' must be"),
    ('ukf', {}, 'method must be one of'),
])
def test_check_refuses_what_the_method_does_not_take(method, options,
                                                     match):
    with pytest.raises(ValueError, match=match):
        MethodOptions(**options).check(method)


def test_a_record_and_keywords_build_the_same_tracker():
    # the record travels whole; keywords beside it replace its fields
    scenario = Scenario.load('paper_test')
    record = MethodOptions(lag=4, tolerance=0.0, iterations=3)
    by_record, key = method_tracker('gbp', scenario, options=record)
    by_keywords, same = method_tracker('gbp', scenario, lag=4, tolerance=0.0,
                                       iterations=3)
    assert key == same == 'gbp-lag4'
    assert by_record.settings() == by_keywords.settings()
    replaced, key = method_tracker('gbp', scenario, options=record, lag=6)
    assert key == 'gbp-lag6' and replaced.lag == 6
