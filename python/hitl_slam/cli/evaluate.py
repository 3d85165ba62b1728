"""``hitl-slam evaluate``: repair damaged worlds and real logs with a simulated person."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.errors import InputError
from hitl_slam.extras import require

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands

EPILOG = """\
examples:
  hitl-slam evaluate                   # everything; a few minutes
  hitl-slam evaluate --quick -o /tmp/e # the lost-poses room and the corridors only
  hitl-slam evaluate --full -j 2       # the harder benchmark: 9 maps x 4 fault models x
                                       # 5 / 15 cm endpoint noise, a careful person
  hitl-slam evaluate --full --maps Orebro,Seattle --faults jump  # a part of it
  hitl-slam evaluate --full -j 2 --faults slip,scale --seed 3    # damage it was not built on
  hitl-slam evaluate --full -j 2 --maps hall                     # a hall with few long walls

The full evaluation's maps: Intel lab, Freiburg 079, Seattle, Orebro, Belgioioso, Edmonton (real
logs), lost poses room, parallel corridors, campus; with --maps also hall (100 x 50 m, booths,
pillars and round stands, its outer walls the only long ones; generated). Its fault models: jump
(30 degrees), drift (15 degrees over the run), bend (10 degrees along the straightest stretch),
laps (two jumps: three copies); with --faults also slip (one step 0.5-1.5 m off) and scale
(every distance 3-6% off). Exit status 0 when every target is met, 1 when one is not.

Real logs are used when ../shared/datasets/laser (beside the repository) is present.
"""


def add_parser(sub: Commands) -> None:
    evaluate = sub.add_parser(
        "evaluate",
        help="repair damaged worlds and real logs with a simulated person; write a report",
        description=(
            "The paper's Results in kind: Table 1 (angles and spacings between known wall pairs), "
            "the inconsistency metric and ATE, before and after a simulated person's corrections, "
            "on the lost-poses room, parallel corridors, a campus, and the corrected Freiburg 079 "
            "and Intel logs (../shared/datasets/laser) damaged by injected faults."
        ),
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    evaluate.add_argument(
        "-o",
        "--output",
        default="hitl-slam-evaluation",
        metavar="DIR",
        help="where to write report.md and the figures (default ./hitl-slam-evaluation)",
    )
    evaluate.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    evaluate.add_argument(
        "--quick", action="store_true", help="only the two small generated scenarios"
    )
    evaluate.add_argument(
        "--full",
        action="store_true",
        help="the harder benchmark (issue 11): every map, every fault model, a careful person; "
        "writes DIR/full.md",
    )
    evaluate.add_argument(
        "--maps", metavar="A,B", help="with --full: only these maps (comma-separated names)"
    )
    evaluate.add_argument(
        "--faults",
        metavar="A,B",
        help="with --full: these fault models (default jump,drift,bend,laps, the issue's four; "
        "also slip: one step's translation off by 0.5-1.5 m, and scale: every distance 3-6%% "
        "off)",
    )
    evaluate.add_argument(
        "--no-align",
        action="store_true",
        help="with --full: the person does not align the map with its scans after drawing",
    )
    evaluate.add_argument(
        "--applier",
        choices=("pipeline", "oracle", "oracle-model"),
        default="pipeline",
        help="with --full: what computes each correction: hitl-slam's own (default); 'oracle', "
        "which knows the observations the person meant (perfect data association, no guard; "
        "docs/ALGORITHM.md §I.14); 'oracle-model', the same with the odometry's true noise as its "
        "information: how often a true correction still makes the map worse",
    )
    evaluate.add_argument(
        "-j", "--jobs", type=int, default=1, help="with --full: runs at once (default 1)"
    )
    evaluate.add_argument("-q", "--quiet", action="store_true", help="only the table")
    evaluate.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from hitl_slam.evaluation import run_evaluation, table

    out = Path(args.output)
    if args.full:
        return _evaluate_full(args, out)
    if args.maps or args.faults or args.no_align or args.applier != "pipeline":
        raise InputError(
            "--maps, --faults, --no-align and --applier are options of the full evaluation; "
            "add --full"
        )
    require("plot", "hitl-slam evaluate")  # the report's figures
    log = (lambda _m: None) if args.quiet else print
    results, report = run_evaluation(out, seed=args.seed, quick=args.quick, log=log)
    print(table(results))
    print(f"report: {report}")
    return 0


def _evaluate_full(args: argparse.Namespace, out: Path) -> int:
    from hitl_slam.evaluation import provenance
    from hitl_slam.full_evaluation import (
        FULL_MAPS,
        full_report,
        run_full,
        runs_json,
        summary,
        targets_met,
    )
    from hitl_slam.io.atomic import atomic_outputs, atomic_write_text
    from hitl_slam.sim.fault_models import FAULT_MODELS, FULL_FAULTS

    maps = [m.strip() for m in args.maps.split(",")] if args.maps else list(FULL_MAPS)
    faults = [f.strip() for f in args.faults.split(",")] if args.faults else list(FULL_FAULTS)
    for f in faults:
        if f not in FAULT_MODELS:
            raise InputError(
                f"--faults: unknown fault model {f!r}; they are: {', '.join(FAULT_MODELS)}"
            )
    total = len(maps) * len(faults) * 2
    done = [0]

    def log(r: object) -> None:
        done[0] += 1
        if not args.quiet:
            from hitl_slam.full_evaluation import Run

            assert isinstance(r, Run)
            print(
                f"[{done[0]}/{total}] {r.map}, {r.fault}, {100 * r.noise_m:.0f} cm: "
                f"{r.accepted}/{len(r.drawings)} accepted, "
                f"{sum(d.worse for d in r.drawings)} worse, "
                f"ATE {r.ate[0]:.3f} -> {r.ate[1]:.3f} m, "
                f"angle {r.angle[0]:.2f} -> {r.angle[1]:.2f} deg"
                + (f", alignment {r.alignment.split(':')[0]}" if r.alignment else "")
                + f", {r.time_s:.0f} s",
                flush=True,
            )

    applier = None
    if args.applier != "pipeline":
        import functools

        from hitl_slam.sim.oracle import oracle_applier

        applier = functools.partial(oracle_applier, error_model=args.applier == "oracle-model")
    start = time.perf_counter()
    runs = run_full(
        seed=args.seed,
        maps=maps,
        faults=faults,
        jobs=args.jobs,
        log=log,
        align=not args.no_align,
        applier=applier,
    )
    out.mkdir(parents=True, exist_ok=True)
    flags = " --full" + (f" --maps {args.maps}" if args.maps else "")
    flags += f" --faults {args.faults}" if args.faults else ""
    flags += " --no-align" if args.no_align else ""
    flags += f" --applier {args.applier}" if args.applier != "pipeline" else ""
    text = full_report(runs, provenance(args.seed, flags, time.perf_counter() - start))
    report = out / "full.md"
    with atomic_outputs():  # the report and its data together
        atomic_write_text(report, text)
        atomic_write_text(out / "full.json", runs_json(runs))
    s = summary(runs)
    print(
        f"accepted {100 * s['accepted_share']:.2f}% of {s['drawings']:.0f} drawings, "
        f"{s['worse']:.0f} made their map worse ({s['worse_beyond_noise']:.0f} beyond the noise), "
        f"{100 * s['achieved']:.0f}% of the achievable "
        f"inconsistency reduction, angle {s['angle_after']:.2f} deg, "
        f"spacing {s['spacing_after']:.3f} m"
    )
    print(f"report: {report}")
    return 0 if all(targets_met(s).values()) else 1
