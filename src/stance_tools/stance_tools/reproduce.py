"""`stance reproduce EXPERIMENT`: rerun an experiment of Raunhardt and Boulic's "Progressive
Clamping" with the Stance PIK (stance.experiments) and write its PNG figures and a table of
numbers (markdown and JSON) into OUTDIR.

- chain: planar 7-joint chain, GPM vs clamping vs progressive clamping (Figs. 9-10).
- thorn: humanoid reaching its right foot behind its back, progressive clamping vs clamping
  (Figs. 11-12) on Talos or on the mannequin of stance.models (--robot), then both again
  over a sweep of lambda and reach gain (thorn_sweep.md).
"""

from __future__ import annotations

from pathlib import Path

ROBOTS = ("talos", "mannequin")


def add_arguments(parser) -> None:
    experiments = parser.add_subparsers(dest="experiment", required=True, metavar="EXPERIMENT")
    chain = experiments.add_parser("chain", help="kinematic chain, Figs. 9-10")
    thorn = experiments.add_parser("thorn", help="humanoid thorn experiment, Figs. 11-12")
    for sub, default in ((chain, "reproduce_chain"), (thorn, "reproduce_thorn")):
        sub.add_argument("-o", "--outdir", type=Path, default=Path(default),
                         help=f"output directory (default: ./{default})")
    thorn.add_argument("--robot", choices=ROBOTS, default="talos",
                       help="humanoid model (default: talos)")


def run(args) -> int:
    if args.experiment == "chain":
        from stance.experiments.chain import reproduce
        paths = reproduce(args.outdir)
    else:
        from stance.experiments.thorn import reproduce
        paths = reproduce(args.outdir, args.robot)
    print(f"{args.experiment}: wrote {len(paths)} files to {args.outdir}")
    for path in paths:
        print(f"  {path}")
    return 0
