"""The stamp rule (issue 14, item 5): not in the future beyond a tolerance, monotonic."""
from __future__ import annotations

import pytest
from sphere_servo.core.stamps import StampRule, StampVerdict

MS = 1_000_000
A, B = 'features/s_n', 'other publisher'


def test_each_outcome_at_and_past_its_bound():
    rule = StampRule(future_tolerance_ns=40 * MS, max_age_ns=500 * MS)
    now = 10_000 * MS
    assert rule.check(A, now + 40 * MS, now).verdict is StampVerdict.ACCEPTED    # at the edge
    rule.forget()
    c = rule.check(A, now + 40 * MS + 1, now)
    assert c.verdict is StampVerdict.FUTURE and c.delta_ns == 40 * MS + 1 and not c.accepted
    assert rule.last(A) is None                    # a refused stamp is not remembered
    assert rule.check(A, now - 500 * MS, now).accepted                           # at the edge
    c = rule.check(A, now - 400 * MS, now)
    assert c.accepted and rule.last(A) == now - 400 * MS
    c = rule.check(A, now - 400 * MS, now)
    assert c.verdict is StampVerdict.REPEAT and c.reference_ns == now - 400 * MS
    c = rule.check(A, now - 400 * MS - 1, now)
    assert c.verdict is StampVerdict.BACKWARDS and c.delta_ns == -1
    rule.forget(A)
    assert rule.check(A, now - 500 * MS - 1, now).verdict is StampVerdict.TOO_OLD


def test_monotonic_per_source_not_across_sources():
    rule = StampRule(future_tolerance_ns=0)
    assert rule.check(A, 2 * MS, 5 * MS).accepted
    assert rule.check(B, 1 * MS, 5 * MS).accepted          # another source, its own order
    assert rule.check(A, 1 * MS, 5 * MS).verdict is StampVerdict.BACKWARDS
    assert rule.check(B, 1 * MS, 5 * MS).verdict is StampVerdict.REPEAT
    assert rule.check(A, 3 * MS, 5 * MS).accepted          # a refusal does not block the next


def test_without_max_age_old_stamps_are_accepted_and_forget_resets():
    rule = StampRule(future_tolerance_ns=0)
    assert rule.check(A, 1, 10 ** 18).accepted
    assert rule.check(A, 0, 10 ** 18).verdict is StampVerdict.BACKWARDS
    rule.forget()                                         # a time jump (replay loop, reset)
    assert rule.check(A, 0, 10 ** 18).accepted


def test_the_order_of_the_tests():
    # a repeat that is also in the future is a repeat (it was accepted once, at its time)
    rule = StampRule(future_tolerance_ns=0, max_age_ns=0)
    assert rule.check(A, 5, 5).accepted
    assert rule.check(A, 5, 1).verdict is StampVerdict.REPEAT
    assert rule.check(A, 4, 100).verdict is StampVerdict.BACKWARDS
    assert rule.check(A, 7, 6).verdict is StampVerdict.FUTURE
    assert rule.check(A, 7, 8).verdict is StampVerdict.TOO_OLD
    assert 'in the future' in str(rule.check(A, 9, 8)) and A in str(rule.check(A, 9, 8))


@pytest.mark.parametrize('kw', [{'future_tolerance_ns': -1}, {'future_tolerance_ns': 0.5},
                                {'future_tolerance_ns': 0, 'max_age_ns': -1}])
def test_bad_rules_are_refused(kw):
    with pytest.raises(ValueError):
        StampRule(**kw)
