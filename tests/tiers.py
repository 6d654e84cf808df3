"""The default tier's share of a parametrized family (the README's
``python -m pytest`` must finish in 10 minutes on 2 cores; most of its
time is numba compiling each compiled-loop variant once: a run type per
dimension, mass kind (lumped or not) and effect kinds, and that type's
loop per scheme).

``tiered(family, cases, ids, default)`` returns the family's cases with
those whose id is not in ``default`` marked ``slow`` (the slow tier runs
the whole list). The default ids are chosen so that every pair of scheme,
mass and dimension of the family's list occurs, and every value of its
other options (effect, degree, material, reconstruction) at least once,
picking the variants other default tests compile anyway;
``tests/test_tiers.py`` checks that for every family registered here."""
import pytest

__all__ = ["FAMILIES", "tiered"]

FAMILIES = {}
"""family name -> (cases, id function, default ids, the options paired,
options: a case's options as a dict)"""


def tiered(family, cases, ids, default, paired=("scheme", "mass", "dim"), options=dict):
    """The cases of ``family``, those not named in ``default`` (ids by
    ``ids``) marked slow; ``options(case)``: the case's options by name."""
    named = {ids(c) for c in cases}
    unknown = set(default) - named
    if unknown:
        raise ValueError(f"{family}: default ids {sorted(unknown)} name no case")
    FAMILIES[family] = (list(cases), ids, frozenset(default), tuple(paired), options)
    slow = pytest.mark.slow(reason=f"{family}: one more compiled variant; the default tier "
                            f"covers every pair of {', '.join(paired)} and every other option")
    return [c if ids(c) in default else pytest.param(c, marks=slow) for c in cases]
