"""The suite's run-time type checks are on: fpe_jax's module-level functions and its classes check
their annotations, shapes included, on every call (tests/conftest.py leaves out only functions
nested in other functions, and says why)."""

import numpy as np
import pytest
from jaxtyping import TypeCheckError

from fpe_jax.geometry import Track, _path


def test_a_module_function_refuses_an_argument_its_annotation_does_not_allow():
    wp = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0]])
    assert _path.nearest_index(np.zeros((1, 2)), wp).tolist() == [0]
    with pytest.raises(TypeCheckError, match="nearest_index"):
        _path.nearest_index([[0.0, 0.0]], wp)


def test_a_class_refuses_a_field_of_the_wrong_shape():
    track = Track.from_waypoints(np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0], [0.0, 10.0]]))
    fields = {**vars(track)}
    assert Track(**fields).xy_m.shape == track.xy_m.shape
    with pytest.raises(TypeCheckError):
        Track(**{**fields, "xy_m": track.xy_m[:, :1]})
