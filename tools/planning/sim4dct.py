"""``tools/sim4dct CONFIG --out PLAN.json [--seed S] [--phases K] [--noise-mm X]``: the plan of the
simulated patient of CONFIG (its ``[simulation.patient]`` phantom and ``[simulation.body]``) with
its planning 4D CT (drivers/sim/planning_ct.py): the fiducials, the skin entry and the target at K
phases of one breath, each with the CT's localisation error. ``hil run CONFIG --plan PLAN.json
--seed S`` with ``[procedure.compensation] target_model = "surrogate"`` then steers by it, and with
``estimator = "pattern"`` follows the entry by it. The seed must be the
run's: the skin field and the target's motion are drawn from it.

Exit 0 with the file written and one line saying what it holds; exit 2 with one line for bad
input (an unreadable config or trace, a rigid phantom, a trace with fewer than 3 breaths in the
minute before the start, fewer than 3 phases). A body driven by a recorded trace
(``[simulation.body.trace]``) gets the CT sorted from the trace's breaths before the start.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from drivers.sim.planning_ct import DEFAULT_CT_NOISE_MM, DEFAULT_PHASES, four_d_ct_plan
from hil.config import load_setup
from hil.errors import HilError
from hil.log import configure_logging


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="tools/sim4dct", description=__doc__.splitlines()[0])
    ap.add_argument("config", help="a simulated setup with a deformable body (e.g. configs/sim_patient.toml)")
    ap.add_argument("--out", required=True, help="the plan JSON to write")
    ap.add_argument("--seed", type=int, help="the simulation seed (default: the config's)")
    ap.add_argument("--phases", type=int, default=DEFAULT_PHASES,
                    help=f"phase bins of the 4D CT, the registered one included (default {DEFAULT_PHASES})")
    ap.add_argument("--noise-mm", type=float, default=DEFAULT_CT_NOISE_MM,
                    help=f"localisation error per axis of each phase's points, mm (default "
                         f"{DEFAULT_CT_NOISE_MM})")
    args = ap.parse_args(argv)
    configure_logging(level="error")
    try:
        setup = load_setup(Path(args.config))
        sim = setup.simulation
        if args.seed is not None:
            sim = sim.model_copy(update={"seed": args.seed})
        doc = four_d_ct_plan(sim, args.phases, args.noise_mm)
        Path(args.out).write_text(json.dumps(doc, indent=1) + "\n")
    except (HilError, ValueError, OSError) as exc:
        print(f"tools/sim4dct: error: {exc}", file=sys.stderr)
        return 2
    print(f"{args.out}: plan of the simulated patient (seed {sim.seed}) with {len(doc['phases'])} phases "
          f"after the registered one")
    return 0


if __name__ == "__main__":
    sys.exit(main())
