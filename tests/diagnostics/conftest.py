"""The diagnosis tests start from conservative fits of damped data: they test that
``diagnose`` finds the damping a fit lacks. Fits with forces whose probes find
damping dominating are otherwise redone jointly (``lagsindy.joint``; its tests:
``tests/test_joint.py``), so every test here fits inside ``conservative_fits()``."""

import pytest

from lagsindy.joint import conservative_fits


@pytest.fixture(autouse=True)
def _conservative_starting_models():
    with conservative_fits():
        yield
