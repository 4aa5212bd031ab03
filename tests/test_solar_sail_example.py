"""examples/solar_sail.py runs end to end in its smoke configuration (one target, a
gradient solver, a metaheuristic and the indirect reference) and writes its table,
record and figures."""

import json
import os

import numpy as np
import pytest
from helpers import load_example


@pytest.mark.slow
def test_solar_sail_example_quick(tmp_path, capsys):
    example = load_example("solar_sail")
    out = str(tmp_path / "sail")
    record = example.main(
        [
            "--quick",
            "--targets",
            "venus",
            "--methods",
            "search",
            "gwo",
            "indirect",
            "--out",
            out,
        ]
    )
    printed = capsys.readouterr().out

    assert sorted(os.listdir(out)) == [
        "results.json",
        "results.md",
        "venus_convergence.png",
        "venus_orbit.png",
        "venus_pitch.png",
    ]
    with open(os.path.join(out, "results.json")) as f:
        assert json.load(f)["arguments"]["segments"] == 4
    ind = record["indirect"]["venus"]
    assert ind["success"] and abs(ind["tf_days"] - 204.18) < 0.01
    methods = {r["method"]: r for r in record["results"]}
    assert set(methods) == {"KalmanSearch", "GreyWolf"}
    gwo = methods["GreyWolf"]
    assert len(gwo["runs"]) == 2 and all(
        r["evaluations"] == 10 * 9 for r in gwo["runs"]
    )  # population x (generations + 1)
    assert np.asarray(gwo["history_best"]).shape == (2, 8)
    for m in record["results"]:
        for r in m["runs"]:
            # every outcome is diagnosed; a restricted control never beats the unrestricted optimum unflagged
            assert isinstance(r["diagnose"]["flags"], list)
            assert r["diagnose"]["flags"] or r["tf"] >= ind["tf"] * (1 - 1e-9)
    # the table: one row for the reference and one per method
    rows = [line for line in printed.splitlines() if line.startswith("| venus |")]
    assert len(rows) == 3 and "indirect" in rows[0]
