"""Every script in examples/ refuses a bad argument (out of range, non-finite, too small, not
a number, an unusable output folder) with argparse's own one-line error and exit status 2,
before any solve: they ended in tracebacks, some after minutes of solving (issue 51:
`closed_loop.py --n 1`, `--sigma-thrust -1`, `--sigma-thrust nan`). Every case runs in one
subprocess (importing the package once, a few seconds), each as `python script.py ARGS`
would (`runpy` as `__main__`, in its own empty folder); the runs themselves are tested in
tests/test_<example>_example.py."""

import json
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


# `--out` naming a file: a traceback at its first write (after the solves) before
OUT_IS_A_FILE = ("attitude", ["--out", "taken"], "argument --out: 'taken' is a file, not a folder")

# Runs each case as `python examples/SCRIPT.py ARGS` would (as `__main__`, with sys.argv and
# its own working folder) and reports the exit code, stderr, stdout and the files left behind.
DRIVER = """
import contextlib, io, json, os, runpy, sys, traceback
root, cases = sys.argv[1], json.loads(sys.argv[2])
sys.path.insert(0, os.path.join(root, "examples"))
results = []
for i, (script, argv, folder) in enumerate(cases):
    os.chdir(folder)
    err, out, code = io.StringIO(), io.StringIO(), None
    path = os.path.join(root, "examples", script + ".py")
    sys.argv = [path, *argv]
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
        try:
            runpy.run_path(path, run_name="__main__")
        except SystemExit as e:
            code = e.code
        except BaseException:
            traceback.print_exc(file=err)
    results.append({"code": code, "stderr": err.getvalue(), "stdout": out.getvalue(), "files": sorted(os.listdir(folder))})
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def outcomes(tmp_path_factory):
    """Every case of CASES, then OUT_IS_A_FILE, run by DRIVER in one subprocess."""
    cases = []
    for i, (script, argv, _) in enumerate([*CASES, OUT_IS_A_FILE]):
        folder = tmp_path_factory.mktemp(f"case{i}")
        cases.append((script, argv, str(folder)))
    with open(os.path.join(cases[-1][2], "taken"), "w") as f:
        f.write("mine")
    env = {**os.environ, "PYTHONPATH": ROOT, "JAXTRAJ_CACHE_DIR": str(tmp_path_factory.mktemp("cache"))}
    r = subprocess.run(
        [sys.executable, "-c", DRIVER, ROOT, json.dumps(cases)], capture_output=True, text=True, env=env, timeout=300
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("i", range(len(CASES)), ids=[f"{s}{' '.join(a)}" for s, a, _ in CASES])
def test_a_bad_argument_is_argparses_one_line_error(i, outcomes):
    script, _, message = CASES[i]
    r = outcomes[i]
    last = r["stderr"].strip().splitlines()[-1] if r["stderr"].strip() else ""
    assert r["code"] == 2 and "Traceback" not in r["stderr"], r["stderr"]
    assert last.startswith(f"{script}.py: error: argument ") and message in last, r["stderr"]
    assert not r["stdout"]  # nothing ran
    assert r["files"] == []  # nothing written


def test_an_out_that_is_a_file_is_refused(outcomes):
    r = outcomes[len(CASES)]
    assert r["code"] == 2 and "Traceback" not in r["stderr"], r["stderr"]
    assert r["stderr"].strip().splitlines()[-1] == f"attitude.py: error: {OUT_IS_A_FILE[2]}"
    assert r["files"] == ["taken"]
