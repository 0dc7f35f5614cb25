"""[method.parameters] values are checked whether or not the method uses them."""

import pytest

from kinefuse.exceptions import ConfigError
from kinefuse.pipelines.run.parameters import _check_params


@pytest.mark.parametrize("method", ["imu-only", "paper-a", "elm-fir"])
@pytest.mark.parametrize("value", ["big", True, [], {"elbow": "x"}])
def test_a_numeric_parameter_that_is_not_a_number_is_refused(method, value):
    with pytest.raises(ConfigError, match=r"\[method.parameters\] q: expected a number"):
        _check_params({"q": value}, method)


@pytest.mark.parametrize("value", [1, 0.5, {"elbow": 0.1, "wrist": 2}, [0.1, 0.2]])
def test_numbers_and_tables_of_numbers_pass(value):
    _check_params({"q": value, "horizon": 20}, "imu-only")
