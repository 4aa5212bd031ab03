"""examples/design_loop.py (issue 50) in a quick mode: Newton through `jt.solve` meets the
required transfer time, converging quadratically (its derivative is the true one), and the
design holds in an independent solve from the naive start; the sensitivities of the table
agree with the secants of the solved tf*(a0) between neighbouring sails."""

import numpy as np
import pytest
from helpers import load_example

import jaxtraj as jt


@pytest.mark.slow  # ~45 s on 2 cores, most of it compiling the differentiated solve twice
def test_design_loop_meets_one_year(tmp_path, capsys):
    example = load_example("design_loop")
    result = example.main(["--grid", "3", "--out", str(tmp_path)])
    printed = capsys.readouterr().out
    days = np.array([tf for _, _, tf, _ in result["rows"]])
    errors = np.abs(days - 365.0)
    assert errors[-1] < 1e-6 and len(days) <= 8
    assert errors[-2] < 0.1 and errors[-1] < 10 * errors[-2] ** 2  # quadratic at the end
    assert result["check_status"] == jt.Status.SUCCESS and abs(result["check_tf_days"] - 365.0) < 1e-6
    table = (tmp_path / "design_loop.md").read_text()
    rows = [line.split("|")[1:-1] for line in table.splitlines() if line.startswith("|") and "SUCCESS" in line]
    a0, tf, slope = (np.array([float(r[i]) for r in rows]) for i in (0, 1, 2))
    secants = np.diff(tf) / np.diff(a0)
    # convex and decreasing: each secant lies between the derivatives at its two ends
    assert np.all((slope[:-1] <= secants) & (secants <= slope[1:])), (slope, secants)
    assert (tmp_path / "design_loop.png").stat().st_size > 10_000 and "Newton" in printed
