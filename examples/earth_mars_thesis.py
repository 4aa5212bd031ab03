"""Reproduce the seven published Earth-Mars tests of the source thesis next to the published
table and the independently computed restricted optima (see `jaxtraj/reproduce.py`).

Prints a Markdown table, writes it to `OUTDIR/earth-mars-thesis.md` and the seven control
histories to `OUTDIR/earth-mars-thesis.png`. Run: `python examples/earth_mars_thesis.py
[OUTDIR [CASE ...]]` (all seven: a few minutes, most of it compilation and the SLSQP
references; e.g. `results 4` solves case 4 alone); the same as `jaxtraj reproduce --out OUTDIR`.
"""

import argparse

from _args import folder, number

import jaxtraj as jt
from jaxtraj.reproduce import main

if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "outdir", nargs="?", type=folder, default="results", help="where the table and figure go (results)"
    )
    # (a type, not `choices`: argparse checks the empty default [] against choices, which
    # refused the documented run of all seven)
    parser.add_argument(
        "cases", nargs="*", type=number(int, 1, 7), metavar="CASE", help="case numbers 1..7 (default: all seven)"
    )
    args = parser.parse_args()
    jt.configure_cpu()  # a CPU device per core and XLA options (before any JAX computation)
    main(args.outdir, *args.cases)
