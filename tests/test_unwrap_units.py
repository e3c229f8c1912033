"""derivatives(..., angles=) checks the unit before unwrapping by 2 pi (#44 item 4)."""

import math
import warnings

import numpy as np
import pytest

from lagsindy.differentiation import _units, derivatives

T = np.arange(400) / 100.0


def _run(q, **kw):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        X = derivatives(q.reshape(len(T), -1), T, method="finite_difference", **kw)
    return X, [str(w.message) for w in caught if "not wraps" in str(w.message)]


def test_radian_angles_wrapped_to_one_turn_unwrap_silently():
    spin = 3.0 * T  # rad, 12 rad in 4 s
    wrapped = (spin + np.pi) % (2 * np.pi) - np.pi
    X, warned = _run(wrapped, angles=[0])
    assert not warned
    np.testing.assert_allclose(X[:, 0], spin, atol=1e-12)


def test_degrees_wrapped_at_180_are_not_unwrapped_silently():
    spin = np.degrees(3.0 * T)  # the same rotation in degrees
    wrapped = (spin + 180) % 360 - 180
    _, warned = _run(wrapped, angles=[0])
    assert len(warned) == 1 and "numpy.deg2rad" in warned[0]
    assert "period=360" in warned[0]


def test_a_fast_swing_in_degrees_warns():
    swing = 80.0 * np.sin(5.0 * T)  # degrees: steps up to 4 per sample (> pi)
    _, warned = _run(swing, angles=[0])
    assert len(warned) == 1 and "0 (steps up to 4" in warned[0]
    # in radians the same swing unwraps nothing and says nothing
    _, warned = _run(np.radians(swing), angles=[0])
    assert not warned


def test_a_slow_swing_in_degrees_is_left_alone():
    swing = 30.0 * np.sin(2.0 * T)  # steps below pi: np.unwrap changes nothing
    X, warned = _run(swing, angles=[0])
    assert not warned
    np.testing.assert_allclose(X[:, 0], swing)


@pytest.mark.parametrize("span, warns", [(1.04, False), (1.06, True)])
def test_boundary_on_the_span_of_a_trajectory(span, warns):
    assert _units.WRAP_SPAN == 1.05
    # a ramp spanning `span` turns with one step of 1.2 pi in its middle
    q = np.linspace(0.0, span * 2 * math.pi - 1.2 * math.pi, T.size)
    q[T.size // 2 :] += 1.2 * math.pi
    _, warned = _run(q, angles=[0])
    assert bool(warned) is warns


def test_each_trajectory_is_checked_on_its_own():
    spin = np.degrees(3.0 * T[:200])
    wrapped = (spin + 180) % 360 - 180
    radians = (3.0 * T[:200] + np.pi) % (2 * np.pi) - np.pi
    q = np.column_stack([np.r_[radians, radians], np.r_[radians, wrapped]])
    groups = np.repeat([0, 1], 200)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        derivatives(q, T, groups=groups, method="finite_difference", angles="all")
    warned = [str(w.message) for w in caught if "not wraps" in str(w.message)]
    assert len(warned) == 1 and warned[0].startswith("angles 1 (")
    assert caught[0].filename == __file__  # points at the caller
