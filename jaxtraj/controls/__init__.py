"""Control parametrizations u(a, t): each family is one class.

Every family splits [0, tf] into `segments` intervals [t_k, t_{k+1}] (the *knots*, which may
be parameters) and defines the control on segment k as a function of the rescaled time
tau = (t - t_k) / (t_{k+1} - t_k) in [0, 1]. Control discontinuities therefore only occur on
segment boundaries, and the simulator integrates each segment on tau, so node times and tf
are smooth parameters of the final state (seed 000 sec. 5.3, seed 003 eq. 6-7).

Parameter layouts follow the thesis (seed 000, sec. 5.3 and Tables 5.1-5.13) where it defines
one; `time_indices` says which entries of `a` are times (node times, durations or tf).
`FixedFinalTime` and `FreeInitialState` adapt a family to a problem with a fixed final time
or free initial states (`Problem.parametrize`).
"""

from ._base import (
    AbstractControl as AbstractControl,
    saturates_within as saturates_within,
    value_bounds as value_bounds,
)
from ._families import (
    PiecewiseConstant as PiecewiseConstant,
    PiecewiseLinear as PiecewiseLinear,
    PiecewiseParabolic as PiecewiseParabolic,
    SaturatedSpline as SaturatedSpline,
    spline_kernel as spline_kernel,
)
from ._wrappers import FixedFinalTime as FixedFinalTime, FreeInitialState as FreeInitialState

__all__ = [
    "AbstractControl",
    "FixedFinalTime",
    "FreeInitialState",
    "PiecewiseConstant",
    "PiecewiseLinear",
    "PiecewiseParabolic",
    "SaturatedSpline",
    "saturates_within",
    "spline_kernel",
    "value_bounds",
]
