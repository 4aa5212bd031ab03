"""Closed-loop simulation and Monte Carlo of the sampled-data LQR loop."""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np

from .._checks import as_float64, check_inputs, check_memory, memory_refusal
from .._simulate import RK4, simulation_status
from .._status import Status, as_indexable
from ._common import check_shape, check_weight, symmetrize
from ._errors import ThrustErrors
from ._linearize import check_execution, check_simulator_rk4
from ._sampled import Noise, bounded_control, check_gains, gain_sequence, noise_free, rollout


def _psd_sqrt(name, M, n):
    """A square root L (L L^T = M) of a symmetric PSD `(n, n)` matrix, by eigh (M may be
    singular)."""
    if M is None:
        return None
    M = as_float64(M)
    check_shape(name, M.shape, (n, n))
    check_weight(name, M)
    w, V = jnp.linalg.eigh(symmetrize(M))
    return V * jnp.sqrt(jnp.maximum(w, 0.0))[None, :]


def _is_zero(value) -> bool:
    """A concrete real scalar 0 (Python, NumPy or JAX; `jnp.asarray(0.0)` was taken for a
    declared error and refused on a problem without a thrust entry)."""
    if isinstance(value, jax.core.Tracer) or isinstance(value, bool):
        return False
    try:
        v = np.asarray(value)
    except (TypeError, ValueError):
        return False
    return v.shape == () and np.issubdtype(v.dtype, np.number) and not np.iscomplexobj(v) and bool(v == 0)


def _noise_model(problem, execution, process_noise, initial_covariance, correlation_time):
    execution = check_execution(execution, problem)
    try:
        c = as_float64(correlation_time)
    except (TypeError, ValueError):  # (JAX's message named no argument)
        raise ValueError(
            f"`correlation_time` must be a number >= 0 (0: white, inf: bias); got {correlation_time!r}."
        ) from None
    if c.ndim != 0:
        raise ValueError(f"`correlation_time` must be a scalar; got shape {c.shape}.")
    if not isinstance(c, jax.core.Tracer) and not bool(c >= 0):
        raise ValueError(f"`correlation_time` must be >= 0 (0: white, inf: bias); got {float(c)}.")
    n = problem.num_states
    return Noise(
        execution=execution,
        num_xi=execution.num_noise(problem.num_controls),
        correlation_time=c,
        Lw=_psd_sqrt("process_noise", process_noise, n),
        L0=_psd_sqrt("initial_covariance", initial_covariance, n),
    )


def _as_key(key):
    """`key` as a PRNG key: a key (typed, or a legacy uint32 pair) as it is, an int seed in
    0..2**64 - 1 through `jax.random.key`, None (no noise) as None; anything else is a
    ValueError naming `key`."""
    if key is None:
        return None
    if isinstance(key, int | np.integer) and not isinstance(key, bool):
        if not 0 <= int(key) < 2**64:
            raise ValueError(f"`key` as an int seed must be in 0..2**64 - 1; got {int(key)}.")
        return jax.random.key(int(key))
    dtype = getattr(key, "dtype", None)
    if dtype is not None and (
        jnp.issubdtype(dtype, jax.dtypes.prng_key) or (dtype == jnp.uint32 and jnp.shape(key)[-1:] == (2,))
    ):
        return key
    raise ValueError(f"`key` must be a JAX PRNG key (jax.random.key(seed)) or an int seed; got {key!r}.")


class ClosedLoopTrajectory(eqx.Module):
    """One closed-loop run on the control-sample grid.

    - `t` `(N + 1,)` sample times; `x` `(N + 1, n)` states; `x_ref` `(N + 1, n)` reference.
    - `u` `(N, m)`: commanded control at the start of each sample, u_ref(t_k) + du_k (before
      execution errors; the feedforward u_ref(t) itself varies inside the sample).
    - `du` `(N, m)`: feedback corrections -K_k (x_k - x_ref_k).
    - `xf` `(n,)`: x(tf); `status`: `Status.NONFINITE` if the run blew up.
    """

    t: jax.Array
    x: jax.Array
    x_ref: jax.Array
    u: jax.Array
    du: jax.Array
    xf: jax.Array
    status: Status = eqx.field(converter=as_indexable)


def simulate_closed_loop(
    problem,
    control,
    a,
    key=None,
    *,
    gains=None,
    execution=None,
    process_noise=None,
    initial_covariance=None,
    correlation_time=0.0,
    simulator=RK4(),
) -> ClosedLoopTrajectory:
    """One run of u = u_ref(t) - K_k (x_k - x_ref_k) with noise; see `monte_carlo` for the
    model and the arguments. `key=None` runs without noise (declared noise is then refused).
    Pure and jit-compiled; vmap it over keys for a batch (or use `monte_carlo`)."""
    a = check_inputs(problem, control, a)
    check_simulator_rk4(simulator)
    N, n, m = control.num_segments * simulator.steps, problem.num_states, problem.num_controls
    gains = check_gains(gains, N, m, n)
    declared = [
        name
        for name, value in (
            ("execution", execution),
            ("process_noise", process_noise),
            ("initial_covariance", initial_covariance),
        )
        if value is not None
    ]
    if key is None and declared:  # (the noise was dropped without a word)
        raise ValueError(
            f"`key` is None (a run without noise), but {', '.join(f'`{d}`' for d in declared)} "
            "declare(s) noise: pass a key (jax.random.key(seed)) to draw it, or leave the noise out."
        )
    noise = _noise_model(problem, execution, process_noise, initial_covariance, correlation_time)
    return _closed_loop(problem, control, a, _as_key(key), gains, noise, simulator.steps)


@eqx.filter_jit
def _closed_loop(problem, control, a, key, gains, noise, steps):
    grid, x_ref = noise_free(problem, control, a, steps)
    K = gain_sequence(gains, grid.t)
    x0, xf, xs, du, _ = rollout(problem, control, noise, grid, x_ref[0], x_ref[:-1], K, key, True)
    rows, h = grid.theta[:, :-2], grid.theta[:, -1]
    u = bounded_control(problem, jax.vmap(control.local_control)(rows, h, grid.tau) + du)
    return ClosedLoopTrajectory(
        t=grid.t,
        x=jnp.concatenate([x0[None], xs]),
        x_ref=x_ref,
        u=u,
        du=du,
        xf=xf,
        status=simulation_status(jnp.array(True), xf),
    )


class Dispersion(eqx.Module):
    """Dispersion of the states over the runs at T band times (the sample times, every
    `dispersion_stride`-th, and tf).

    `t` `(T,)`; `reference`, `mean`, `std` `(T, n)`; `percentiles` `(P, T, n)` at the levels
    `levels` `(P,)` (in percent). Runs that blew up are left out.
    """

    t: jax.Array
    reference: jax.Array
    mean: jax.Array
    std: jax.Array
    percentiles: jax.Array
    levels: jax.Array


class MonteCarloResult(eqx.Module):
    """Terminal statistics of `monte_carlo` runs.

    Per run (leading axis = the runs, in the order of their keys):

    - `final_states` `(runs, n)`: x(tf) at the nominal tf;
    - `terminal_errors` `(runs, l)`: E = M(tf, x(tf)) (`problem.terminal`), 0 = on target;
    - `correction_rms` `(runs, m)`: root mean square over [0, tf] of the feedback correction
      du (zeros in open loop);
    - `finite` `(runs,)`: False for a run whose final state or E is not finite.

    Statistics over the finite runs (`num_failed` = the others): `terminal_mean` `(l,)`,
    `terminal_covariance` `(l, l)` (unbiased), `terminal_std` `(l,)`, `terminal_percentiles`
    `(P, l)` at `levels` (percent); `state_mean` `(n,)`, `state_covariance` `(n, n)` of
    x(tf). `reference_final_state`, `reference_terminal`: the noise-free run. `tf`: the
    nominal final time. `dispersion`: a `Dispersion` if `return_trajectories=True`, else None.
    """

    tf: jax.Array
    reference_final_state: jax.Array
    reference_terminal: jax.Array
    final_states: jax.Array
    terminal_errors: jax.Array
    correction_rms: jax.Array
    finite: jax.Array
    num_failed: jax.Array
    terminal_mean: jax.Array
    terminal_covariance: jax.Array
    terminal_std: jax.Array
    terminal_percentiles: jax.Array
    state_mean: jax.Array
    state_covariance: jax.Array
    levels: jax.Array
    dispersion: Dispersion | None


def monte_carlo(
    problem,
    control,
    a,
    key,
    n: int,
    *,
    gains=None,
    sigma_thrust=0.0,
    sigma_pointing_deg=0.0,
    execution=None,
    process_noise=None,
    initial_covariance=None,
    correlation_time=0.0,
    percentiles=(2.5, 16.0, 50.0, 84.0, 97.5),
    return_trajectories: bool = False,
    dispersion_stride: int = 1,
    simulator=RK4(),
    first_run: int = 0,
) -> MonteCarloResult:
    """Statistical simulation of the open or closed loop around the trajectory of `a` (how
    seed 001 §2 estimates the terminal accuracy of a synthesized control): `n` noisy runs in
    one jitted, vmapped call.

    **Model.** One control sample = one step of `simulator` (`jt.RK4(steps)`, the default
    100 steps per segment; case-5 Earth-Mars: 700 samples of ~0.8 day). On sample k,
    [t_k, t_{k+1}], one classical RK4 step integrates

        x' = f(t, x, u_actual, args_actual) + w_k,
        (u_actual, args_actual) = execution(t, u_ref(t) + du_k, xi_k, args),
        du_k = -K_k (x_k - x_ref_k)       (0 in open loop),

    with the feedforward u_ref(t) evaluated at every RK4 stage and du_k, xi_k, w_k held
    constant over the sample (a sampled-data controller with zero-order hold, which measures
    the full state at t_k). The commanded control is clipped to the problem's control bounds,
    if any. The runs end at the nominal tf (also for free-final-time problems).

    - Execution noise xi_k ~ N(0, I): white across samples (`correlation_time=0`), or the
      stationary first-order Gauss-Markov sequence xi_k = phi_k xi_{k-1} +
      sqrt(1 - phi_k^2) eta_k, phi_k = exp(-dt_k / correlation_time); `inf` is a constant
      bias per run.
    - Process noise: w_k ~ N(0, W / dt_k), white, so its effect over one sample has covariance
      ~ W dt_k: the discretization of white noise of intensity W on dx/dt.
    - Initial state x0 ~ N(problem.x0, initial_covariance) (optional).
    - Reference x_ref: the same sampled run without noise (the arithmetic of `jt.simulate`'s
      RK4 solution; bit for bit on CPU), so a noise-free closed loop reproduces it exactly.

    **Randomness.** Run i uses `jax.random.fold_in(key, i)`: results are reproducible, and the
    first runs of a larger study are the same runs. `first_run` = k runs k, ..., k + n - 1
    instead: a large study in chunks (the CLI's progress lines) gives the same runs.

    **Arguments:**

    - `problem`, `control`, `a`: the nominal (typically `a = sol.params`).
    - `key`: a JAX PRNG key (or an int seed); `n`: number of runs (static; >= 2).
    - `gains`: None (open loop), `LQRGains` (K(t_k) at the sample times), `DiscreteLQRGains`
      or an array `(N, m, n)` with one gain per sample (see `tracking_lqr`).
    - `sigma_thrust`, `sigma_pointing_deg`: shorthand for
      `execution=ThrustErrors(sigma_thrust, sigma_pointing_deg)` (relative thrust-magnitude
      error and pointing error in degrees, 1 sigma; the thrust magnitude is
      `problem.args["thrust"]`, the angle `u[0]`). With `sigma_thrust=0` the pointing error
      needs no thrust entry.
    - `execution`: an `AbstractExecutionErrors` (`ThrustErrors`, `ControlErrors`,
      `ExecutionErrors`); not together with the shorthand.
    - `process_noise`: W `(n, n)` PSD, the intensity of white noise on dx/dt.
    - `initial_covariance`: `(n, n)` PSD.
    - `correlation_time`: of the execution noise (0: white per sample; `jnp.inf`: bias).
    - `percentiles`: levels in percent for the statistics.
    - `return_trajectories`: also return `Dispersion` bands (keeps all `n` trajectories in
      memory inside the call: n (N + 1) n_x float64).
    - `dispersion_stride`: bands on every `dispersion_stride`-th sample time (and tf); the
      percentiles are a sort over the runs at each band time, the costliest part of the call
      with bands (e.g. 7 on 700 samples: 101 band times).
    - `simulator`: `jt.RK4(steps)`; it sets the sample rate.
    - `first_run`: the index of the first run (0; see Randomness).

    **Returns:** `MonteCarloResult`.
    """
    a = check_inputs(problem, control, a)
    check_simulator_rk4(simulator)
    if key is None:  # (JAX's TypeError deep inside the runs)
        raise ValueError("`key` must be a JAX PRNG key (jax.random.key(seed)) or an int seed; got None.")
    if not (isinstance(n, int) and not isinstance(n, bool) and n >= 2):
        raise ValueError(f"`n` must be an int >= 2; got {n!r}.")
    if not (isinstance(first_run, int | np.integer) and not isinstance(first_run, bool) and 0 <= first_run):
        raise ValueError(f"`first_run` must be an int >= 0; got {first_run!r}.")
    shorthand = [not _is_zero(s) for s in (sigma_thrust, sigma_pointing_deg)]
    if any(shorthand):
        if execution is not None:
            raise ValueError("pass either `execution` or `sigma_thrust` / `sigma_pointing_deg`, not both.")
        execution = ThrustErrors(sigma_thrust, sigma_pointing_deg, thrust_key="thrust" if shorthand[0] else None)
    N, nx, m = control.num_segments * simulator.steps, problem.num_states, problem.num_controls
    kept = nx + problem.num_constraints + (nx * (N + 1) if return_trajectories else 0)
    check_memory("n", 8 * n * kept, f"{n:,} runs ({kept} numbers each)")
    if first_run + n > 2**32:
        raise ValueError(f"`first_run` + `n` must be <= 2**32 (run indices are uint32); got {first_run + n:,}.")
    gains = check_gains(gains, N, m, nx)
    noise = _noise_model(problem, execution, process_noise, initial_covariance, correlation_time)
    levels = as_float64(percentiles)
    if levels.ndim != 1 or not bool(jnp.all((levels >= 0) & (levels <= 100))):
        raise ValueError(f"`percentiles` must be a 1-d sequence in [0, 100]; got {percentiles!r}.")
    if not (isinstance(dispersion_stride, int) and dispersion_stride >= 1):
        raise ValueError(f"`dispersion_stride` must be an int >= 1; got {dispersion_stride!r}.")
    with memory_refusal("jt.monte_carlo", "use a smaller n or fewer RK4 steps"):
        return _monte_carlo(
            problem,
            control,
            a,
            _as_key(key),
            n,
            gains,
            noise,
            simulator.steps,
            levels,
            dispersion_stride if return_trajectories else 0,
            jnp.asarray(int(first_run), dtype=jnp.uint32),
        )


def masked_stats(values, finite, levels):
    """Mean, unbiased covariance and percentiles over the leading axis of `values` `(R, d)`,
    leaving out the rows where `finite` is False."""
    count = jnp.sum(finite).astype(values.dtype)  # (a float: it divides the values)
    keep = finite[:, None]
    mean = jnp.sum(jnp.where(keep, values, 0.0), axis=0) / count
    d = jnp.where(keep, values - mean[None], 0.0)
    cov = symmetrize(d.T @ d / jnp.where(count >= 2, count - 1, jnp.nan))  # (NaN, not 0, without two runs)
    pct = jnp.nanpercentile(jnp.where(keep, values, jnp.nan), levels, axis=0)
    return mean, cov, pct


@eqx.filter_jit
def _monte_carlo(problem, control, a, key, n, gains, noise, steps, levels, stride, first):
    """`stride` (static): 0 = no dispersion bands, else bands every `stride` samples; `first`
    (traced, uint32): the index of the first run."""
    save = stride > 0
    grid, x_ref = noise_free(problem, control, a, steps)
    K = gain_sequence(gains, grid.t)
    tf = grid.t[-1]

    def run(i):
        x0, xf, xs, _, du2 = rollout(
            problem, control, noise, grid, x_ref[0], x_ref[:-1], K, jax.random.fold_in(key, i), save
        )
        return xf, (jnp.concatenate([x0[None], xs]) if xs is not None else None), du2  # (xs: None unless save)

    xfs, xs, du2 = jax.vmap(run)(first + jnp.arange(n, dtype=jnp.uint32))
    E = jax.vmap(lambda xf: problem.terminal(tf, xf, problem.args))(xfs)
    finite = jnp.all(jnp.isfinite(xfs), axis=1) & jnp.all(jnp.isfinite(E), axis=1)
    E_mean, E_cov, E_pct = masked_stats(E, finite, levels)
    x_mean, x_cov, _ = masked_stats(xfs, finite, levels[:0])
    dispersion = None
    if xs is not None:  # (save: the runs' states came back)
        N = grid.tau.shape[0]
        idx = np.unique(np.append(np.arange(0, N + 1, stride), N))
        xs = jnp.where(finite[:, None, None], xs[:, idx], jnp.nan)
        dispersion = Dispersion(
            t=grid.t[idx],
            reference=x_ref[idx],
            mean=jnp.nanmean(xs, axis=0),
            std=jnp.nanstd(xs, axis=0, ddof=1),
            percentiles=jnp.nanpercentile(xs, levels, axis=0),
            levels=levels,
        )
    return MonteCarloResult(
        tf=tf,
        reference_final_state=x_ref[-1],
        reference_terminal=problem.terminal(tf, x_ref[-1], problem.args),
        final_states=xfs,
        terminal_errors=E,
        correction_rms=jnp.sqrt(du2 / tf),
        finite=finite,
        num_failed=n - jnp.sum(finite),
        terminal_mean=E_mean,
        terminal_covariance=E_cov,
        terminal_std=jnp.sqrt(jnp.diag(E_cov)),
        terminal_percentiles=E_pct,
        state_mean=x_mean,
        state_covariance=x_cov,
        levels=levels,
        dispersion=dispersion,
    )
