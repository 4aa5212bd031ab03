"""Every script in examples/ refuses a bad argument (out of range, non-finite, too small, not
a number, an unusable output folder) with argparse's own one-line error and exit status 2,
before any solve: they ended in tracebacks, some after minutes of solving (issue 51:
`closed_loop.py --n 1`, `--sigma-thrust -1`, `--sigma-thrust nan`). Each case is one
subprocess that only imports the package (a few seconds); the runs themselves are tested in
tests/test_<example>_example.py."""

import os
import subprocess
import sys

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

CASES = [
    ("closed_loop", ["--n", "1"], "--n: must be in 2..1,000,000; got 1"),
    ("closed_loop", ["--sigma-thrust", "-1"], "--sigma-thrust: must be finite and >= 0; got -1"),
    ("closed_loop", ["--sigma-thrust", "nan"], "--sigma-thrust: must be finite and >= 0; got nan"),
    ("closed_loop", ["--correlation-time", "nan"], "--correlation-time: must be >= 0; got nan"),
    ("closed_loop", ["--seed", str(2**70)], "--seed: must be in 0..9,223,372,036,854,775,807"),
    ("closed_loop", ["--out", ""], "--out: must not be empty"),
    ("attitude", ["--segments", "0"], "--segments/-P: must be in 1..1,000; got 0"),
    ("attitude", ["--max-steps", "1e9"], "--max-steps: expected an int; got '1e9'"),
    ("solar_sail", ["--population", "2"], "--population: must be in 3..100,000; got 2"),
    ("solar_sail", ["--pitches", "20", "nan"], "--pitches: must be >= 0 and <= 90; got nan"),
    ("solar_sail", ["--tf-factors", "0"], "--tf-factors: must be > 0 and <= 2; got 0"),
    ("solar_sail", ["--penalty-weight=-inf"], "--penalty-weight: must be finite and > 0; got -inf"),
    ("design_loop", ["--days", "inf"], "--days: must be finite and > 0; got inf"),
    ("inverse_control", ["--steps", "0"], "--steps: must be in 1..1,000,000; got 0"),
    ("inverse_control", ["--noise", "nan"], "--noise: must be finite and >= 0; got nan"),
    ("earth_mars_thesis", [""], "argument outdir: must not be empty"),
]


# one case per script in the fast tier (a subprocess each, ~4 s); the rest with the slow studies
_seen = set()
PARAMS = []
for _s, _a, _m in CASES:
    PARAMS.append(pytest.param(_s, _a, _m, id=f"{_s}{' '.join(_a)}", marks=() if _s not in _seen else pytest.mark.slow))
    _seen.add(_s)


@pytest.mark.parametrize(("script", "argv", "message"), PARAMS)
def test_a_bad_argument_is_argparses_one_line_error(script, argv, message, tmp_path):
    env = {**os.environ, "PYTHONPATH": ROOT, "JAXTRAJ_CACHE_DIR": str(tmp_path / "cache")}
    r = subprocess.run(
        [sys.executable, os.path.join(ROOT, "examples", f"{script}.py"), *argv],
        capture_output=True,
        text=True,
        env=env,
        cwd=tmp_path,
        timeout=120,
    )
    last = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert last.startswith(f"{script}.py: error: argument ") and message in last, r.stderr
    assert not r.stdout  # nothing ran
    assert [p.name for p in tmp_path.iterdir() if p.name != "cache"] == []  # nothing written


def test_an_out_that_is_a_file_is_refused(tmp_path):
    """`--out` naming a file: a traceback at its first write (after the solves) before."""
    (tmp_path / "taken").write_text("mine")
    r = subprocess.run(
        [sys.executable, os.path.join(ROOT, "examples", "attitude.py"), "--out", "taken"],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": ROOT},
        cwd=tmp_path,
        timeout=120,
    )
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1] == "attitude.py: error: argument --out: 'taken' is a file, not a folder"
