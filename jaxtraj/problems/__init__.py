"""Problem families: `earth_mars` (seed 000) and small problems with analytic answers."""

from . import analytic as analytic, earth_mars as earth_mars
