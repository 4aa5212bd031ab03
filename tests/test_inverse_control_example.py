"""examples/inverse_control.py (issue 50): gradient descent (optax) through `jt.solve`
recovers the damping and the cost weight that generated an observed optimal trajectory
(the truth is known: it made the record), from a guess 3.5x and 6x off."""

import pytest
from helpers import load_example


@pytest.mark.slow  # ~25 s on 2 cores: 300 differentiated solves, one compilation
def test_inverse_control_recovers_damping_and_weight(capsys):
    example = load_example("inverse_control")
    result = example.main(["--steps", "300"])
    assert abs(result["c"] - 0.7) < 1e-5 and abs(result["q"] - 3.0) < 1e-4
    loss = result["history"][:, 3]
    assert loss[-1] < 1e-10 * loss[0]
    assert "recovered c = 0.700000" in capsys.readouterr().out
