"""groomtool.deprecation.rename_field on the params classes whose sweep budget was renamed max_iterations ->
max_sweeps (issue 18): the old keyword and attribute still work, with a DeprecationWarning."""

import dataclasses
import warnings

import pytest

from groomtool.invert import InversionParams
from groomtool.simulate import SimulationParams


@pytest.mark.parametrize("cls", [InversionParams, SimulationParams])
def test_max_iterations_is_a_deprecated_alias_of_max_sweeps(cls):
    with pytest.warns(DeprecationWarning, match="max_sweeps"):
        params = cls(max_iterations=7)
    assert params.max_sweeps == 7 and params == cls(max_sweeps=7)
    with pytest.warns(DeprecationWarning, match="max_sweeps"):
        assert params.max_iterations == 7
    with pytest.raises(AttributeError):
        params.max_iterations = 3
    with pytest.raises(ValueError, match="max_sweeps"):
        cls(max_sweeps=0)
    with pytest.raises(TypeError), pytest.warns(DeprecationWarning):
        cls(max_sweeps=7, max_iterations=7)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a copy with a new budget: no warning, and the new budget kept
        assert dataclasses.replace(params, max_sweeps=9).max_sweeps == 9
