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


@pytest.mark.slow  # ~15 s: the compilation of the differentiated solve
def test_an_overflowing_loss_stops_the_fit():
    """`--noise 1e300`: the loss overflowed to inf and the script printed the guess as the
    "recovered" values, exit 0 (issue 51, third audit)."""
    example = load_example("inverse_control")
    with pytest.raises(SystemExit, match=r"step 0: the loss is inf .*no fit with --noise 1e\+300"):
        example.main(["--steps", "3", "--noise", "1e300"])
