"""Command line: `jaxtraj problems | solve PROBLEM [...] | reproduce`.

PROBLEM is a built-in problem (`jaxtraj problems` lists them) or a user's own,
`path/to/file.py:function` or `package.module:function`: the function, called without
arguments, returns a `jt.Problem` (then `--control` and `--tf` make the start: a zero control
over [0, tf]) or a tuple `(problem, control, a0)`.

No JAX work at import time; every failure the user can cause ends in a one-line
`jaxtraj: error: ...` message and exit code 2, never a traceback.
"""

import argparse
import contextlib
import datetime
import hashlib
import importlib
import importlib.util
import io as io_module
import os
import sys
import time

_PROBLEMS = {
    "earth-mars": "Minimum-time low-thrust planar Earth-Mars transfer (source thesis, 7 published cases).",
    "min-energy": "Minimum-energy rest-to-rest double integrator in fixed time (analytic optimum 6).",
    "solar-sail": "Minimum-time solar-sail Earth-to-Mars-orbit transfer (Kelley's anchor, SaturatedSpline(10, 1)).",
    "attitude": "Minimum-energy 500 s attitude slew with a 50 deg sun keep-out cone (quaternions, 8 segments).",
}
_CONTROLS = (
    "linear:K (continuous, nodes at fixed fractions of tf), linear-free:K (jumps, free node times), "
    "parabolic:K, constant:K (free switch times), each with :Q for Q channels (e.g. linear:8:2), "
    "spline:P:DEGREE:LOWER:UPPER"
)


class _UsageError(Exception):
    pass


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line, no usage dump
        raise _UsageError(message)


def _parser():
    p = _Parser(prog="jaxtraj", description="Trajectory optimization by control restriction.")
    sub = p.add_subparsers(dest="command", required=True, parser_class=_Parser)
    sub.add_parser("problems", help="list the available problems and controls")
    s = sub.add_parser("solve", help="solve a problem and write results")
    s.add_argument(
        "problem", help=f"one of: {', '.join(_PROBLEMS)}; or your own, path/to/file.py:function or module:function"
    )
    g = s.add_mutually_exclusive_group()
    g.add_argument("--case", type=int, help="earth-mars: published thesis case 1..7 (default 4)")
    g.add_argument("--control", help=f"control spec: {_CONTROLS}")
    s.add_argument(
        "--tf",
        type=float,
        default=None,
        help="your own problem: final time of the zero-control start (default 1; a problem's final_time wins)",
    )
    s.add_argument(
        "--solver",
        help="default: the problem's own (earth-mars, min-energy, solar-sail: kalman; attitude and your own: sqp); "
        "kalman (the thesis's Kalman-filter search, published tuning), sqp (KalmanSQP's default: exact "
        "Hessian, trust region; sqp-tr the same), sqp-exact (KalmanSQP, exact Hessian, line search), "
        "sqp-bfgs (KalmanSQP, BFGS, line search)",
    )
    s.add_argument("--starts", type=int, default=1, help="number of starting vectors (vmapped)")
    s.add_argument("--seed", type=int, default=None, help="seed of the random extra starts and Monte Carlo runs (0)")
    s.add_argument(
        "--monte-carlo",
        type=int,
        default=0,
        metavar="N",
        help="after the solve: N noisy runs (1%% thrust magnitude, 1 deg pointing), open loop vs "
        "time-varying LQR closed loop (earth-mars)",
    )
    s.add_argument(
        "--resume",
        action="store_true",
        help="with --starts > 1 and the --out of an interrupted run: skip the chunks already solved",
    )
    s.add_argument("--steps", type=int, default=100, help="RK4 steps per segment")
    s.add_argument("--max-steps", type=int, default=5000, help="cap on candidate integrations")
    s.add_argument("--out", help="result folder (default results/<problem>-<timestamp>)")
    s.add_argument("--no-plot", action="store_true", help="do not write figures")
    r = sub.add_parser("reproduce", help="the seven published Earth-Mars cases vs the thesis")
    r.add_argument("--out", default="results/reproduce", help="result folder")
    return p


#: Upper limits of the size options, checked before anything is allocated (beyond them
#: memory or compile time explode; a larger study belongs in Python with jt.solve_batch).
LIMITS = {
    "starts": 1_000_000,
    "steps": 10_000,
    "max_steps": 1_000_000,
    "segments": 1_000,
    "channels": 1_000,
    "monte_carlo": 1_000_000,
}


def _positive(name, value, limit=None):
    if value < 1:
        raise _UsageError(f"{name} must be >= 1; got {value}")
    if limit is not None and value > limit:
        raise _UsageError(f"{name} must be <= {limit:,}; got {value:,}")


def parse_control(spec):
    """A control family from a spec string such as `linear:5` or `spline:4:3:-1.5:1.5`."""
    import jaxtraj as jt

    parts = spec.split(":")
    kind, rest = parts[0], parts[1:]
    try:
        nums = [float(x) if i >= 2 else int(x) for i, x in enumerate(rest)]
    except ValueError:
        raise _UsageError(f"malformed control spec {spec!r}: expected {_CONTROLS}") from None
    makers = {
        "linear": ((1, 2), lambda k, q=1: jt.controls.PiecewiseLinear(k, channels=q)),
        "linear-free": (
            (1, 2),
            lambda k, q=1: jt.controls.PiecewiseLinear(k, continuous=False, free_times=True, channels=q),
        ),
        "parabolic": ((1, 2), lambda k, q=1: jt.controls.PiecewiseParabolic(k, channels=q)),
        "constant": ((1, 2), lambda k, q=1: jt.controls.PiecewiseConstant(k, channels=q)),
        "spline": ((4,), lambda p, d, lo, hi: jt.controls.SaturatedSpline(p, d, lo, hi)),
    }
    if kind not in makers:
        raise _UsageError(f"unknown control {kind!r} in {spec!r}: expected {_CONTROLS}")
    counts, make = makers[kind]
    if len(nums) not in counts:
        raise _UsageError(f"malformed control spec {spec!r}: expected {_CONTROLS}")
    # (checked before the family is made: a huge count reached NumPy, whose error was a traceback)
    sizes = [("segments", nums[0])] + ([("channels", nums[1])] if kind != "spline" and len(nums) == 2 else [])
    for what, value in sizes:
        if value > LIMITS[what]:
            raise _UsageError(f"--control {spec!r}: at most {LIMITS[what]:,} {what}; got {value:,}")
    try:
        return make(*nums)
    except ValueError as e:
        raise _UsageError(f"control spec {spec!r}: {e}") from None


def _parametrize(prob, spec):
    """`prob.parametrize` of the family named by `spec`, its refusal as a usage error."""
    import jaxtraj as jt

    family = parse_control(spec)
    if prob.final_time is not None and isinstance(family, jt.controls.SaturatedSpline):
        # a fixed final time takes tf as one entry, not free durations (the spec cannot say so)
        family = jt.controls.SaturatedSpline(
            family.segments, family.degree, family.lower, family.upper, free_durations=False
        )
    try:
        return prob.parametrize(family)
    except ValueError as e:
        raise _UsageError(f"--control {spec}: {e}") from None


_SOLVERS = ("kalman", "sqp", "sqp-exact", "sqp-tr", "sqp-bfgs")


def _setup(problem_name, args):
    import jax.numpy as jnp
    import numpy as np

    import jaxtraj as jt

    if problem_name == "earth-mars":
        EM = jt.problems.earth_mars
        if args.control:
            prob = EM.problem()
            ctrl = parse_control(args.control)
            a0 = ctrl.initial_guess(3.4, 0.0, 1.5 * np.pi)
            solver = jt.KalmanSearch()
            label = args.control
        else:
            case = 4 if args.case is None else args.case
            if case not in range(1, 8):
                raise _UsageError(f"--case must be in 1..7; got {case}")
            prob, ctrl, a0 = EM.thesis_case(case)
            solver = EM.thesis_solver(case)
            label = f"case {case}"
        return prob, ctrl, jnp.asarray(a0), solver, label, float(EM.CONSTANTS["rf"])
    if args.case is not None:
        raise _UsageError("--case applies to earth-mars only")
    if problem_name == "solar-sail":
        sail = jt.problems.solar_sail
        prob, ctrl, a0 = sail.kelley_case()
        if args.control:
            ctrl = parse_control(args.control)
            a0 = ctrl.initial_guess(7.0, 0.6, 0.6)
        return prob, ctrl, jnp.asarray(a0), sail.kalman_search_solver(), args.control or "Kelley", None
    if problem_name == "attitude":
        prob, ctrl, a0 = jt.problems.attitude.case()
        if args.control:
            ctrl = parse_control(args.control)
            a0 = ctrl.initial_guess(float(prob.args["tf"]), 0.0, 0.0)  # the maneuver time, solver units
        return prob, ctrl, jnp.asarray(a0), jt.KalmanSQP(), args.control or "8 segments", None
    if problem_name == "min-energy":
        prob = jt.problems.analytic.min_energy_double_integrator()
        ctrl = parse_control(args.control or "linear:3")
        return (
            prob,
            ctrl,
            jnp.asarray(ctrl.initial_guess(1.2, 0.0, 0.0)),
            jt.KalmanSearch(),
            args.control or "linear:3",
            None,
        )
    if problem_name in _gallery().names():
        entry = _gallery().get(problem_name)
        prob, ctrl, a0 = entry.problem, entry.control, entry.start
        if args.control:
            ctrl = _parametrize(prob, args.control)
            tf = float(entry.control.tf(entry.start))  # the naive start's final time
            try:
                a0 = ctrl.initial_guess(tf, 0.0, 0.0)
            except ValueError as e:
                raise _UsageError(f"--control: {e}") from None
        return prob, ctrl, jnp.asarray(a0), jt.KalmanSQP(), args.control or "naive start", None
    prob, ctrl, a0 = load_user_problem(problem_name, args)
    return prob, ctrl, a0, jt.KalmanSQP(), args.control or "own start", None  # a0 checked by the caller


def _user_function(spec):
    """The function named by `path/to/file.py:function` or `package.module:function`."""
    where, _, name = spec.rpartition(":")
    if not where or not name.isidentifier():
        raise _UsageError(f"unknown problem {spec!r}; available: {', '.join(_PROBLEMS)}, or path/to/file.py:function")
    try:
        if where.endswith(".py"):
            if not os.path.isfile(where):
                what = "is a folder, not a file" if os.path.isdir(where) else "not found"
                raise _UsageError(f"problem file {where!r} {what}")
            # a module name that is the same in every process (`hash` is salted per process)
            key = hashlib.sha256(os.path.abspath(where).encode()).hexdigest()[:16]
            module_spec = importlib.util.spec_from_file_location(f"_jaxtraj_user_{key}", where)
            assert module_spec is not None and module_spec.loader is not None  # (a .py file has a source loader)
            module = importlib.util.module_from_spec(module_spec)
            # its own folder on sys.path, as `python file.py` would have it (a problem file
            # that imports a helper module beside it, at import or in its function)
            home = os.path.dirname(os.path.abspath(where))
            if home not in sys.path:
                sys.path.insert(0, home)
            module_spec.loader.exec_module(module)
        else:
            module = importlib.import_module(where)
    except _UsageError:
        raise
    except SystemExit as e:  # the module ended the process while importing: nothing was solved
        raise _UsageError(f"importing {where!r} called sys.exit({e.code!r}); nothing was solved") from None
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # the user's module failed to import (any exception): one line
        raise _UsageError(f"importing {where!r} failed: {type(e).__name__}: {e}") from None
    fn = getattr(module, name, None)
    if not callable(fn):
        raise _UsageError(f"{where!r} has no function {name!r}")
    return fn


def load_user_problem(spec, args):
    """`(problem, control, a0)` from a user's function (see the module docs)."""
    import jaxtraj as jt

    fn = _user_function(spec)
    try:
        out = fn()
    except SystemExit as e:
        raise _UsageError(f"{spec} called sys.exit({e.code!r}); nothing was solved") from None
    except KeyboardInterrupt:
        raise
    except BaseException as e:  # (a user's own BaseException subclass too)
        raise _UsageError(f"{spec} raised {type(e).__name__}: {e}") from None
    if isinstance(out, jt.Problem):
        prob, ctrl, a0 = out, None, None
    elif isinstance(out, tuple) and len(out) == 3 and isinstance(out[0], jt.Problem):
        prob, ctrl, a0 = out
    else:
        raise _UsageError(f"{spec} must return a jt.Problem or (problem, control, a0); got {type(out).__name__}")
    if ctrl is not None and not args.control and args.tf is not None:
        raise _UsageError(f"--tf: {spec} returns its own start; --tf sets the zero-control start (with --control)")
    if args.tf is not None and prob.final_time is not None:
        raise _UsageError(f"--tf: {spec} has a fixed final_time ({float(prob.final_time):g})")
    if ctrl is None or args.control:  # a zero control over [0, --tf]
        ctrl = _parametrize(prob, args.control or f"linear:10:{prob.num_controls}")
        tf = (1.0 if args.tf is None else args.tf) if prob.final_time is None else float(prob.final_time)
        try:
            a0 = ctrl.validate(ctrl.initial_guess(tf, 0.0, 0.0))
        except ValueError as e:
            raise _UsageError(f"--tf {tf:g}: {e}") from None
    return prob, ctrl, a0


#: What this command holds until it exits: the lock on its --out folder.
_HELD = contextlib.ExitStack()


def _remove_if_empty(folder):
    try:
        os.rmdir(folder)
    except OSError:  # not empty (the results, a batch to resume) or already gone
        pass


def _new_folder(base):
    """The first of `base`, `base-2`, `base-3`, ... that this process creates (two runs
    started in the same second get a folder each); removed at exit if left empty."""
    try:
        os.makedirs(os.path.dirname(base) or ".", exist_ok=True)
        for k in range(1, 1000):
            folder = base if k == 1 else f"{base}-{k}"
            try:
                os.mkdir(folder)
            except FileExistsError:
                continue
            _HELD.callback(_remove_if_empty, folder)
            return folder
    except OSError as e:
        raise _UsageError(f"cannot create a result folder {base!r} ({e.strerror or e}); pass --out") from None
    raise _UsageError(f"no free result folder {base}-N; pass --out")


def _check_out(folder):
    """Create --out, check it is writable and lock it for this run (`io.folder_lock`). A
    folder this run created and left empty (it failed before writing) is removed at exit."""
    from .io import folder_lock

    try:
        try:
            os.makedirs(folder)
            _HELD.callback(_remove_if_empty, folder)  # runs after the lock's release
        except FileExistsError:
            pass
        probe = os.path.join(folder, ".write-test")
        with open(probe, "w") as f:
            f.write("")
        os.remove(probe)
        _HELD.enter_context(folder_lock(folder, "--out"))
    except OSError as e:
        raise _UsageError(f"cannot write to --out {folder!r}: {e.strerror or e}") from None
    except ValueError as e:
        raise _UsageError(str(e)) from None


def _monte_carlo(prob, ctrl, sol, sim, args):
    """Open vs closed loop (sampled time-varying LQR, Bryson weights) terminal dispersion for
    1 % thrust-magnitude and 1 deg pointing errors; prints a table, returns the numbers."""
    import jax
    import numpy as np

    import jaxtraj as jt

    errors = jt.ThrustErrors(0.01, 1.0)
    lin = jt.linearize(prob, ctrl, sol.params, simulator=sim, execution=errors)
    gains = jt.tracking_lqr(lin, *jt.bryson_weights(lin, 1e-3, 0.05, 1e-4))
    key = jax.random.key(args.seed)
    print(
        f"Monte Carlo: {args.monte_carlo} runs each, 1 % thrust magnitude and 1 deg pointing errors "
        "(white per control sample), LQR with Bryson weights",
        flush=True,
    )
    runs = {
        name: _monte_carlo_runs(name, prob, ctrl, sol, key, args.monte_carlo, g, errors, sim)
        for name, g in (("open loop", None), ("closed loop", gains))
    }
    print(f"  {'terminal error':<22}" + "".join(f"{n + ' mean':>18}{n + ' std':>18}" for n in runs))
    for i, name in enumerate(prob.constraint_names):
        row = "".join(f"{r['mean'][i]:>18.3e}{r['std'][i]:>18.3e}" for r in runs.values())
        print(f"  {name:<22}{row}")
    traces = {n: float(np.trace(r["covariance"])) for n, r in runs.items()}
    ratio = traces["closed loop"] / traces["open loop"]
    print(f"  covariance trace: open {traces['open loop']:.3e}, closed {traces['closed loop']:.3e} (ratio {ratio:.4f})")
    return {
        "runs": args.monte_carlo,
        "sigma_thrust": 0.01,
        "sigma_pointing_deg": 1.0,
        **{
            n: {
                "mean": r["mean"].tolist(),
                "std": r["std"].tolist(),
                "covariance_trace": traces[n],
                "failed": r["failed"],
            }
            for n, r in runs.items()
        },
        "trace_ratio": ratio,
    }


#: Monte Carlo runs per compiled call: a larger --monte-carlo runs in 10 chunks, a progress
#: line each on stderr (1,000,000 runs took minutes without a word).
MONTE_CARLO_CHUNK = 20_000


def _monte_carlo_runs(name, prob, ctrl, sol, key, n, gains, errors, sim):
    """`jt.monte_carlo`'s terminal statistics of `n` runs (mean, std, covariance, failed),
    in chunks of the same runs (`first_run`) above `MONTE_CARLO_CHUNK`, with a line per chunk."""
    import numpy as np

    import jaxtraj as jt

    size = n if n <= MONTE_CARLO_CHUNK else -(-n // 10)
    chunks = -(-n // size)
    E, finite = np.empty((n, prob.num_constraints)), np.empty(n, bool)
    t0 = time.perf_counter()
    for k in range(chunks):
        lo, hi = k * size, min((k + 1) * size, n)
        first = min(lo, n - size)  # the last chunk as large as the others (one compiled program)
        r = jt.monte_carlo(
            prob, ctrl, sol.params, key, size, gains=gains, execution=errors, simulator=sim, first_run=first
        )
        E[lo:hi] = np.asarray(r.terminal_errors)[lo - first :]
        finite[lo:hi] = np.asarray(r.finite)[lo - first :]
        if chunks > 1:
            elapsed = time.perf_counter() - t0
            print(
                f"monte carlo, {name}: {hi:,}/{n:,} runs (chunk {k + 1}/{chunks}) | {elapsed:.1f} s | "
                f"{hi / elapsed:,.0f} runs/s | failed {int(np.sum(~finite[:hi]))}",
                file=sys.stderr,
                flush=True,
            )
    from .feedback._monte_carlo import masked_stats  # (`jt.monte_carlo`'s statistics: finite runs only)

    mean, cov, _ = (np.asarray(x) for x in masked_stats(E, finite, np.zeros(0)))
    return {"mean": mean, "std": np.sqrt(np.diag(cov)), "covariance": cov, "failed": n - int(finite.sum())}


def _gallery():
    """`jt.problems.classic` (imported on demand: it imports JAX)."""
    from .problems import classic

    return classic


def _solve(args):
    known = (*_PROBLEMS, *_gallery().names())
    if args.problem not in known and ":" not in args.problem:
        raise _UsageError(
            f"unknown problem {args.problem!r}; available: {', '.join(known)}, or path/to/file.py:function"
        )
    if args.solver is not None and args.solver not in _SOLVERS:
        raise _UsageError(f"unknown solver {args.solver!r}; available: {', '.join(_SOLVERS)}")
    if args.monte_carlo == 1 or not 0 <= args.monte_carlo <= LIMITS["monte_carlo"]:
        raise _UsageError(
            f"--monte-carlo must be 0 (none) or 2..{LIMITS['monte_carlo']:,} runs; got {args.monte_carlo:,}"
        )
    if args.seed is not None and not 0 <= args.seed < 2**63:
        raise _UsageError(f"--seed must be in 0..2**63 - 1; got {args.seed}")
    if args.monte_carlo and args.problem != "earth-mars":
        raise _UsageError("--monte-carlo needs thrust errors: earth-mars only")
    for name in ("starts", "steps", "max_steps"):
        _positive(f"--{name.replace('_', '-')}", getattr(args, name), LIMITS[name])
    if args.resume and args.starts == 1:
        raise _UsageError("--resume continues a batch of starts (--starts N > 1); one start has nothing to resume")
    if args.seed is not None and args.starts == 1 and not args.monte_carlo:
        raise _UsageError("--seed draws the extra starts (--starts N > 1) and the Monte Carlo runs; there are none")
    args.seed = 0 if args.seed is None else args.seed
    if args.tf is not None and ":" not in args.problem:
        raise _UsageError(f"--tf sets the start of your own problem (file.py:function); {args.problem} has its own")
    for name in ("out", "control"):
        if getattr(args, name) == "":
            raise _UsageError(f"--{name} must not be empty")
    stamp = datetime.datetime.now().strftime("%Y%m%d-%H%M%S")
    slug = args.problem if args.problem in known else args.problem.rpartition(":")[2]
    out = args.out or _new_folder(os.path.join("results", f"{slug}-{stamp}"))
    _check_out(out)

    import jax
    import numpy as np

    import jaxtraj as jt
    from jaxtraj import io
    from jaxtraj.plot import batch_figure, write_figures

    from ._cache import default_cache_folder, enable_compilation_cache

    enable_compilation_cache(default_cache_folder())
    from ._checks import check_inputs

    prob, ctrl, a0, solver, label, r_target = _setup(args.problem, args)
    try:
        a0 = check_inputs(prob, ctrl, a0)
    except ValueError as e:
        raise _UsageError(f"{args.problem}: {e}") from None
    if args.solver == "kalman" and not isinstance(solver, jt.KalmanSearch):
        solver = jt.KalmanSearch()  # the problem's own tuning where it has one
    elif args.solver in ("sqp", "sqp-tr"):
        solver = jt.KalmanSQP()
    elif args.solver == "sqp-exact":
        solver = jt.KalmanSQP(globalization="line-search")
    elif args.solver == "sqp-bfgs":
        solver = jt.KalmanSQP(hessian="bfgs", globalization="line-search")
    sim = jt.RK4(args.steps)
    print(f"{args.problem} ({label}): {ctrl!r}, {ctrl.num_params} parameters, RK4({args.steps})", flush=True)
    print(f"compiling and solving {args.starts} start(s) ...", flush=True)
    t0 = time.perf_counter()
    sols = None
    if args.starts == 1:
        start = np.asarray(a0)
    else:
        # random starts around a0 (a0 itself first), one compiled batch solve in up to 10
        # chunks (a progress line each, on stderr), each chunk written to <out>/batch so that
        # --resume can pick an interrupted run up
        starts = np.array(jt.random_starts(prob, ctrl, jax.random.key(args.seed), args.starts, around=a0, spread=0.05))
        starts[0] = np.asarray(a0)
        try:
            sols = jt.solve_batch(
                prob,
                ctrl,
                starts,
                solver,
                simulator=sim,
                max_steps=args.max_steps,
                chunk_size=-(-args.starts // 10),
                out=os.path.join(out, "batch"),
                resume=args.resume,
                history=False,
            )
        except OSError as e:  # a full disk while writing a chunk: the chunks written so far are kept
            raise _UsageError(
                f"writing to --out {out!r} failed ({e.strerror or e}); --resume continues the run"
            ) from None
        except ValueError as e:  # the batch folder: another run, changed inputs, a damaged file
            message = str(e).splitlines()[0]
            message = message.replace("pass resume=True", "pass --resume").replace("`resume`", "--resume")
            raise _UsageError(message.replace("`out`", "--out")) from None
        ok = np.asarray(sols.status == jt.Status.SUCCESS)
        start = starts[int(np.argmin(np.where(ok, np.asarray(sols.objective), np.inf))) if ok.any() else 0]
        print(
            f"  {int(ok.sum())} / {args.starts} starts successful ({time.perf_counter() - t0:.1f} s); "
            "the best one again alone, for its history:",
            flush=True,
        )
    try:
        best = jax.block_until_ready(
            jt.solve(prob, ctrl, start, solver, simulator=sim, max_steps=args.max_steps, progress=100)
        )
    except ValueError as e:  # what the solver cannot honour (e.g. bounds on a parabolic control)
        raise _UsageError(f"{args.problem}: {str(e).splitlines()[0]}") from None
    ok_count = int(best.status == jt.Status.SUCCESS) if sols is None else int(ok.sum())
    first = time.perf_counter() - t0
    second = None
    if first <= WARM_RERUN_LIMIT:  # the warm time: the same compiled solve again, silenced
        t0 = time.perf_counter()
        with contextlib.redirect_stdout(io_module.StringIO()):
            jax.block_until_ready(
                jt.solve(prob, ctrl, start, solver, simulator=sim, max_steps=args.max_steps, progress=100)
            )
        second = time.perf_counter() - t0
    try:
        traj = jt.simulate(prob, ctrl, best.params, simulator=sim)
    except ValueError as e:  # (parameters a solver ended at that jt.simulate refuses: no traceback)
        raise _UsageError(
            f"{args.problem}: the solve ended {jt.status_name(best.status)} at parameters that cannot be "
            f"simulated: {str(e).splitlines()[0]}"
        ) from None

    rows = [
        ("status", jt.status_name(best.status)),
        ("successful starts", f"{ok_count} / {args.starts}"),
        ("tf", f"{float(best.tf):.8f}"),
        ("objective", f"{float(best.objective):.8f}"),
        ("max violation (all constraints)", f"{float(best.max_violation):.2e}"),
        ("max |terminal equality|", f"{float(best.max_constraint_error):.2e}"),
    ]
    rows += [(f"  {n}", f"{e:+.2e}") for n, e in zip(prob.constraint_names, np.asarray(best.constraints))]
    rows += [
        ("projected gradient", f"{float(best.projected_gradient):.2e}"),
        ("iterations / integrations", f"{int(best.iterations)} / {int(best.integrations)}"),
        (
            "time (warm, best start)",
            f"{second:.3f} s" if second is not None else f"not run (first call > {WARM_RERUN_LIMIT:g} s)",
        ),
        ("time (first call" + (", all starts" if sols is not None else "") + ", incl. compile)", f"{first:.2f} s"),
    ]
    width = max(len(k) for k, _ in rows)
    for k, v in rows:
        print(f"  {k:<{width}}  {v}")
    if args.monte_carlo:
        summary_mc = _monte_carlo(prob, ctrl, best, sim, args)
    inputs = {
        "problem": args.problem,
        "control": repr(ctrl),
        "label": label,
        "a0": np.asarray(a0),
        "starts": args.starts,
        "seed": args.seed,
        "resume": args.resume,
        "rk4_steps": args.steps,
        "max_steps": args.max_steps,
        "solver": repr(solver),
        "versions": {"jaxtraj": jt.__version__, "jax": jax.__version__, "python": sys.version.split()[0]},
    }
    written = ["summary.json", "arrays.npz"]
    try:
        with io.staged_folder(out, "--out") as stage:  # the files appear together or not at all
            io.save(
                stage, prob, best, traj, inputs=inputs, extra={"monte_carlo": summary_mc} if args.monte_carlo else None
            )
            if not args.no_plot:
                written += write_figures(
                    stage,
                    prob,
                    ctrl,
                    best,
                    traj,
                    r_target=r_target,
                    title=f"{args.problem} ({label}): tf = {float(best.tf):.6f}, {jt.status_name(best.status)}",
                )
                if sols is not None:
                    ok_idx = np.flatnonzero(ok)[:50]
                    trajs = [jt.simulate(prob, ctrl, sols.params[i], simulator=sim) for i in ok_idx]
                    batch_figure(
                        os.path.join(stage, "starts.png"),
                        prob,
                        sols.objective,
                        ok,
                        trajs,
                        title=f"{args.problem} ({label}): {args.starts} starts",
                    )
                    written.append("starts.png")
    except OSError as e:  # a full disk, a quota: the result is lost, the folder is as it was
        raise _UsageError(
            f"writing the results to --out {out!r} failed ({e.strerror or e}); it holds what it held before"
        ) from None
    if sols is None:  # an earlier batch run's chunks are no part of this result (mixed results)
        _remove_earlier_batch(os.path.join(out, "batch"))
    print(f"wrote {', '.join(written)} to {out}")
    return 0 if best.status == jt.Status.SUCCESS else 1


def _remove_earlier_batch(folder):
    """Remove the `batch` folder (chunks and manifest) an earlier run with --starts N left in
    --out, after a single-start result replaced that run's summary: the rerun leaves nothing
    of the earlier run (its figures go with `io.staged_folder`'s listing). A folder without
    a batch manifest is not jaxtraj's and stays."""
    import shutil

    if not os.path.isfile(os.path.join(folder, "manifest.json")) or os.path.islink(folder):
        return
    try:
        shutil.rmtree(folder)
    except OSError as e:
        print(f"jaxtraj: warning: could not remove the earlier run's {folder} ({e.strerror or e})", file=sys.stderr)


def _reproduce(args):
    _check_out(args.out)
    from ._cache import default_cache_folder, enable_compilation_cache

    enable_compilation_cache(default_cache_folder())
    from jaxtraj.reproduce import main as reproduce_main

    reproduce_main(args.out)
    return 0


#: The warm time is measured by solving again only where the first call took at most this
#: many seconds (a slow solve is not run twice).
WARM_RERUN_LIMIT = 10.0


class _ReaderGone:
    """stdout that outlives its reader: once a write meets a closed pipe (`jaxtraj solve ... |
    head`) or fails (a full disk under `> file`), further output goes to /dev/null and `gone`
    holds the error, so that a finished solve still writes its results before the command
    ends (141, the shell's code for SIGPIPE, after a closed pipe)."""

    def __init__(self, stream):
        self.stream, self.gone = stream, None

    def _guard(self, call, *args):
        if self.gone is None:
            try:
                return call(*args)
            except OSError as e:
                self.gone = e
                os.dup2(os.open(os.devnull, os.O_WRONLY), self.stream.fileno())  # no second error at exit

    def write(self, text):
        self._guard(self.stream.write, text)
        return len(text)

    def flush(self):
        self._guard(self.stream.flush)

    def __getattr__(self, name):
        return getattr(self.stream, name)


def main(argv=None):
    from ._configure import configure_cpu_if_possible

    configure_cpu_if_possible()  # a device per core and XLA's options (jt.configure_cpu)
    stdout = sys.stdout
    guarded = sys.stdout = _ReaderGone(stdout)
    try:
        code = _main(argv)
    finally:
        sys.stdout = stdout
    if isinstance(guarded.gone, BrokenPipeError):
        return 141
    if guarded.gone is not None:
        print(f"jaxtraj: error: writing to stdout failed ({guarded.gone.strerror or guarded.gone})", file=sys.stderr)
        return 1
    return code


def _main(argv):
    try:
        args = _parser().parse_args(argv)
        if args.command == "problems":
            for name, text in _PROBLEMS.items():
                print(f"{name:12s} {text}")
            print("\nclassic gallery (jt.problems.classic; reference optimum, features):")
            classic = _gallery()
            for name in classic.names():
                entry = classic.get(name)
                print(f"{name:28s} {entry.reference:<10.7g} {', '.join(entry.features)}")
            print()
            print(
                "your own: path/to/file.py:function or module:function (returns a jt.Problem or (problem, control, a0))"
            )
            print(f"\ncontrols (--control): {_CONTROLS}")
            print("earth-mars --case N: the thesis's seven published parametrizations (1..7)")
            return 0
        if args.command == "solve":
            return _solve(args)
        return _reproduce(args)
    except (_UsageError, MemoryError) as e:  # (MemoryError: jaxtraj's own, with its numbers)
        print(f"jaxtraj: error: {str(e).splitlines()[0] if str(e) else 'out of memory'}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxtraj: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of the output left (`jaxtraj problems | head`)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no second error at exit
        return 141
    finally:
        _HELD.close()


if __name__ == "__main__":
    sys.exit(main())
