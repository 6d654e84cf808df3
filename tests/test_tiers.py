"""The default tier keeps every family's coverage (tests/tiers.py): every
pair of values of the paired options (scheme, mass, dimension) that the
family's full list has, and every value of its other options."""
import itertools

import pytest

import test_compiled_loop  # noqa: F401  (each registers its families)
import test_compiled_loop_modifiers  # noqa: F401
import test_compiled_loop_tables  # noqa: F401
import test_executors  # noqa: F401
from tiers import FAMILIES


@pytest.mark.parametrize("family", sorted(FAMILIES))
def test_the_default_tier_covers_the_family(family):
    cases, ids, default, paired, options = FAMILIES[family]
    every = [options(c) for c in cases]
    kept = [options(c) for c in cases if ids(c) in default]
    names = sorted({n for c in every for n in c})
    for name in names:
        assert {c.get(name) for c in kept} == {c.get(name) for c in every}, name
    for a, b in itertools.combinations([n for n in names if n in paired], 2):
        assert {(c.get(a), c.get(b)) for c in kept} == \
            {(c.get(a), c.get(b)) for c in every}, (a, b)
