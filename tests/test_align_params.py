"""The rays method's tuning is one frozen object passed in (align.params.RaysParams)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import align
from align.params import DEFAULT_PARAMS, RaysParams
from twin.sim.bench import BenchSim


@pytest.fixture(scope="module")
def scan():
    return BenchSim(seed=4).scan()


def test_the_defaults_are_the_estimate_without_params(scan):
    plain = align.estimate(scan)
    given = align.estimate(scan, params=RaysParams())
    assert plain.success and given.success
    assert np.array_equal(plain.pose.as_array(), given.pose.as_array())
    assert np.array_equal(plain.covariance, given.covariance)


def test_a_field_changed_reaches_the_steps_that_read_it(scan):
    # the result's step: more brackets asked for than any board gives
    strict = align.estimate(scan, params=dataclasses.replace(DEFAULT_PARAMS,
                                                             min_brackets=10**6))
    assert strict.status == align.Status.PARTIAL_BOARD
    assert "edge brackets" in strict.diagnostics["reason"]
    # the plane's step: a wider trim keeps more returns in the plane's fit
    wide = align.estimate(scan, params=dataclasses.replace(DEFAULT_PARAMS, trim=4.0))
    assert wide.success
    assert not np.array_equal(wide.pose.as_array(), align.estimate(scan).pose.as_array())


def test_params_are_frozen_and_documented():
    with pytest.raises(dataclasses.FrozenInstanceError):
        DEFAULT_PARAMS.trim = 3.0  # type: ignore[misc]
    # every field carries its reason: the source has a "#:" comment block above each
    import inspect

    source = inspect.getsource(RaysParams).splitlines()
    for f in dataclasses.fields(RaysParams):
        line = next(i for i, s in enumerate(source) if s.strip().startswith(f"{f.name}:"))
        above = [s.strip() for s in source[max(0, line - 3):line]]
        assert any(s.startswith("#:") for s in above) or f.name in {
            "min_dropouts", "behind_min", "behind_run", "start_band_sigmas", "stray_spacings",
            "max_stray_fraction", "stray_rounds"}, f.name
