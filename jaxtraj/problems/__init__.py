"""Problem families: `earth_mars` (seed 000), `solar_sail` (seed 003), `attitude` (seed 002),
small problems with analytic answers (`analytic`) and the classic-problem gallery (`classic`)."""

from . import (
    analytic as analytic,
    attitude as attitude,
    classic as classic,
    earth_mars as earth_mars,
    solar_sail as solar_sail,
)
