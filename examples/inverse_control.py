"""Inverse optimal control: recover a model's damping and a cost weight from an observed
optimal trajectory, by gradient descent (optax) through `jt.solve`.

The system is a damped cart, x'' = -c x' + u, moved from rest at 0 to rest at 1 in time 1
while minimizing int (u^2 + q x^2) dt / 2. Someone flew the optimal control of the true
(c, q) = (0.7, 3.0) and recorded the position at 41 instants (with noise of 1e-4 if asked).
We know the form of the model, not c and q: the loss is the squared misfit between the
record and the optimal trajectory of (c, q), and its gradient comes from the implicit
function theorem at each solve's optimum (docs/differentiable.md) chained with the
simulation's derivative. Each solve is warm-started at the previous optimum; the loss and
its gradient are one compiled program.

Run: `python examples/inverse_control.py [--steps 300] [--noise 0]`. Prints the iterations
and the recovered (c, q) next to the truth.
"""

import argparse
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from _args import number

import jaxtraj as jt

if __name__ == "__main__":
    jt.configure_cpu()  # a CPU device per core and XLA options (before any JAX computation)

TRUTH = {"c": 0.7, "q": 3.0}
SAMPLES = jnp.linspace(0.0, 1.0, 41)


def setup():
    prob = jt.Problem(
        lambda t, x, u, a: jnp.stack([x[1], -a["c"] * x[1] + u[0]]),
        jnp.zeros(2),
        lambda tf, xf, a: xf - jnp.array([1.0, 0.0]),
        ("x", "v"),
        num_controls=1,
        running_cost=lambda t, x, u, a: 0.5 * (u[0] ** 2 + a["q"] * x[0] ** 2),
        final_time=1.0,
        args={k: jnp.asarray(v) for k, v in TRUTH.items()},
        name="damped cart",
    )
    ctrl = prob.parametrize(jt.controls.PiecewiseLinear(8))
    return prob, ctrl, jt.RK4(10), jnp.zeros(ctrl.num_params)


def positions(prob, ctrl, sim, args, start):
    """x(t) at SAMPLES on the optimal trajectory of `args`, and the solve's (params, status)."""
    p = eqx.tree_at(lambda p: p.args, prob, args)
    sol = jt.solve(p, ctrl, start, simulator=sim, max_steps=200)
    traj = jt.simulate(p, ctrl, sol.params, simulator=sim)
    return jnp.interp(SAMPLES, traj.t, traj.x[:, 0]), (sol.params, sol.status)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=number(int, 1, 1_000_000), default=300, help="gradient steps")
    parser.add_argument("--noise", type=number(float, 0.0), default=0.0, help="std of the recording noise")
    opts = parser.parse_args(argv)
    t0 = time.perf_counter()
    prob, ctrl, sim, start = setup()
    record, _ = positions(prob, ctrl, sim, prob.args, start)
    record = record + opts.noise * jax.random.normal(jax.random.key(0), record.shape)

    @jax.jit
    def loss_and_grad(theta, start):
        # log-parameters keep c and q positive
        def loss(theta):
            x, aux = positions(prob, ctrl, sim, {k: jnp.exp(v) for k, v in theta.items()}, start)
            return jnp.mean((x - record) ** 2) / 1e-6, aux

        return jax.value_and_grad(loss, has_aux=True)(theta)

    theta = {"c": jnp.log(0.2), "q": jnp.log(0.5)}  # a guess far from the truth
    optimizer = optax.adam(0.05)
    state = optimizer.init(theta)
    print(f"recovering (c, q) = {tuple(TRUTH.values())} from {SAMPLES.size} positions, start (0.2, 0.5)")
    history = []
    for k in range(opts.steps):
        (value, (start, status)), grad = loss_and_grad(theta, start)
        if status != jt.Status.SUCCESS:
            raise SystemExit(f"step {k}: the solve ended {jt.status_name(status)}")
        if not (np.isfinite(float(value)) and all(bool(jnp.all(jnp.isfinite(g))) for g in grad.values())):
            # (a huge --noise: the loss overflowed and the "recovered" values were the guess)
            raise SystemExit(
                f"step {k}: the loss is {float(value)} (its gradient non-finite); no fit with --noise {opts.noise:g}"
            )
        history.append((k, float(jnp.exp(theta["c"])), float(jnp.exp(theta["q"])), float(value)))
        if k % 50 == 0 or k == opts.steps - 1:
            print(f"  step {k:4d}: c = {history[-1][1]:.6f}, q = {history[-1][2]:.6f}, loss {float(value):.3e}")
        # (optax's Adam raises a float to its int32 step count: standard promotion for that
        # call, so the script also runs where strict promotion is on, as in the tests)
        with jax.numpy_dtype_promotion("standard"):
            updates, state = optimizer.update(grad, state)
        theta = optax.apply_updates(theta, updates)
    c, q = (float(jnp.exp(theta[k])) for k in ("c", "q"))
    print(
        f"recovered c = {c:.6f} (true {TRUTH['c']}), q = {q:.6f} (true {TRUTH['q']}) in {time.perf_counter() - t0:.1f} s"
    )
    return {"c": c, "q": q, "history": np.array(history)}


if __name__ == "__main__":
    main()
