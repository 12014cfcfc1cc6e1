"""The suite's run-time type checks are on: fpe_jax's module-level functions and its classes check
their annotations, shapes included, on every call (tests/conftest.py leaves out only functions
nested in other functions, applies the typechecker directly in modules without jaxtyping's array
annotations, and says why)."""

import numpy as np
import pytest
from beartype.roar import BeartypeCallHintParamViolation
from jaxtyping import TypeCheckError

from fpe_jax.fit import _report
from fpe_jax.geometry import Track, _path
from fpe_jax.runner import Runner


def test_a_module_function_refuses_an_argument_its_annotation_does_not_allow():
    wp = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    assert _path.nearest_index(np.zeros((1, 2)), wp).tolist() == [0]
    with pytest.raises(BeartypeCallHintParamViolation, match="nearest_index"):
        _path.nearest_index([[0.0, 0.0]], wp)


def test_a_method_of_the_jax_free_runner_is_checked():
    with pytest.raises(BeartypeCallHintParamViolation, match="Runner.__init__"):
        Runner("not a config", np.zeros((4, 2)))


def test_a_hint_naming_a_class_of_another_module_in_full_is_checked():
    """`_report` names the fit's result in full (its module is imported only for type checkers):
    the check finds the class once the module is loaded and refuses anything else."""
    import fpe_jax.fit._fit  # noqa: F401  (what a fit has loaded before it reports)

    with pytest.raises(BeartypeCallHintParamViolation, match="format_fitted"):
        _report.format_fitted({"params": None})


def test_a_class_refuses_a_field_of_the_wrong_shape():
    track = Track.from_waypoints(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
    fields = {**vars(track)}
    assert Track(**fields).xy_m.shape == track.xy_m.shape
    with pytest.raises(TypeCheckError):
        Track(**{**fields, "xy_m": track.xy_m[:, :1]})
