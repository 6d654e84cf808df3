"""Test tiers: the default tier, ``slow`` (run by CI too) and ``exhaustive``
(full option products; collected only when ``-m`` names it)."""


def pytest_collection_modifyitems(config, items):
    if "exhaustive" in (config.getoption("-m") or ""):
        return
    kept = [item for item in items if item.get_closest_marker("exhaustive") is None]
    if len(kept) != len(items):
        config.hook.pytest_deselected(items=[i for i in items if i not in kept])
        items[:] = kept
