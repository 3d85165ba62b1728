"""``hitl-slam correct``: apply a file of human corrections (JSON Lines) to a map."""

from __future__ import annotations

import argparse
import os
import sys
import time
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from hitl_slam.cli.common import (
    BAGS_NOTE,
    add_bag_options,
    add_force,
    add_max_range,
    check_map_output,
    load_map,
    one_line,
    outputs_of,
    refuse_overwriting_inputs,
    with_progress,
)
from hitl_slam.errors import InputError

if TYPE_CHECKING:
    from hitl_slam.cli.common import Commands
    from hitl_slam.session import Session

EPILOG = """\
examples:
  hitl-slam correct map.covars --corrections fixes.jsonl -o fixed.covars
  hitl-slam correct run.clf.gz --corrections fixes.jsonl -o fixed.g2o --session run.hitl
  hitl-slam correct map.covars --corrections fixes.jsonl -o fixed.pgm --keep-going

MAP is a .covars file, a CARMEN log (.clf/.log, optionally .gz/.bz2), a ROS bag (.bag, .db3,
.mcap or a ROS 2 bag directory; see "ROS bags" below) or a session (.hitl, its current map). The
corrections file has one JSON object per line, applied in order, each on the
map as it stands after the previous ones:

  {"mode": "collinear", "a": [[1.20, 3.40], [4.10, 3.45]], "b": [[10.0, 3.9], [13.2, 4.0]]}
  {"mode": "colocation", "a": [[0, 0], [0, 2]], "b": [[5, 1], [5, 3]], "sigma_h": 0.08}
  {"action": "undo"}

mode is colocation, collinear, perpendicular or parallel; a and b are the two drawn segments
(world frame, metres); sigma_h is the drawing accuracy in metres. Blank lines are skipped; there
are no comments. A session's applied corrections are exported in this form by
`hitl-slam export SESSION.hitl -o C.jsonl`.

A correction that cannot be interpreted (no observations under a segment, interleaved pose sets),
an undo with nothing to undo and a redo with nothing to redo are rejected. Without --keep-going
the run stops at the first one with exit code 2 and writes nothing; with --keep-going they are
skipped and listed, and the rest still apply (exit code 0 once OUT is written).

--align, once every line is done, aligns the map with its scans (docs/ALGORITHM.md §I.11): the
scan-matching front end runs again from the corrected poses, its matched steps and loop closures
replace the map's factors, and every correction is solved again over them. The person's
statements bring copies of a wall together; the scans then close the last centimetres. Where the
aligned map contradicts the robot's odometry at more than 5% of the steps (scan matching gone
wrong: few features, a fault not yet corrected), where the scans found no loop closure between
the passes, or where the aligned map is no more consistent than the map, it is refused with the
figures: exit code 2, nothing written.

OUT's extension picks its format (.covars, .clf CARMEN log, .g2o, .txt TUM, .pgm + .yaml
occupancy grid, .png or .svg figure). --session also keeps the whole run as a session file (a new
file; an existing one is never overwritten) that `hitl-slam serve` or `hitl-slam export` can
open. OUT and the session file are written together or not at all; OUT may not be MAP or C.jsonl
(the same file, also through a link) unless --force. "moved" counts the poses a step moved by
more than 1 mm or 1 mrad.
"""


def add_parser(sub: Commands) -> None:
    correct = sub.add_parser(
        "correct",
        help="apply a file of human corrections (JSON Lines) to a map",
        description="Apply scripted corrections to a map, in order, as a person would in the UI.",
        epilog=EPILOG + BAGS_NOTE,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    correct.add_argument(
        "map", metavar="MAP", help="input map (.covars, .clf/.log, ROS bag, .hitl)"
    )
    add_max_range(correct)
    add_bag_options(correct)
    correct.add_argument(
        "--corrections", required=True, metavar="C.jsonl", help="corrections, one per line"
    )
    correct.add_argument("-o", "--output", required=True, metavar="OUT", help="output map file")
    correct.add_argument(
        "--session", metavar="S.hitl", help="also write the run as a new session file"
    )
    correct.add_argument(
        "--keep-going",
        action="store_true",
        help="skip (and list) rejected corrections instead of stopping at the first",
    )
    correct.add_argument(
        "--align",
        action="store_true",
        help="after the corrections, align the map with its scans: match them again from the "
        "corrected poses and solve every correction over that graph (refused, and nothing "
        "written, where it contradicts the odometry, finds no loop closure or is no more "
        "consistent)",
    )
    add_force(correct)
    correct.add_argument("-q", "--quiet", action="store_true", help="only the summary line")
    correct.set_defaults(func=run)


def _align_session(args: argparse.Namespace, session: Session) -> None:
    """``--align``: the session's map aligned with its scans, with a progress bar over the
    scans; a refusal stops the command (nothing written) with its figures."""
    from hitl_slam.alignment import AlignmentRefused
    from hitl_slam.session import moved_poses

    bar = None
    if not args.quiet and sys.stderr.isatty():
        from tqdm import tqdm

        bar = tqdm(total=session.input_map.num_poses, desc="aligning", unit="scan", file=sys.stderr)

    def progress(done: int, _total: int) -> None:
        if bar is not None:
            bar.n = done
            bar.refresh()

    before = session.poses
    try:
        step = session.align(progress=progress)
    except AlignmentRefused as exc:
        raise InputError(
            f"--align: {exc}; nothing was written (drop --align to write the corrected map)"
        ) from None
    finally:
        if bar is not None:
            bar.close()
    if not args.quiet:
        moved, _ = moved_poses(before, session.poses)
        print(
            f"{'':>5}  {'align':<14} {moved:>7} {step.stats.initial_chi2:>16.6f} "
            f"{step.stats.final_chi2:>16.6f} {1e3 * step.stats.time_s:>9.2f}"
        )
        print(
            f"       aligned with the scans: {step.loop_closures} loop closures kept "
            f"({step.loop_closures_rejected} rejected); the aligned map contradicts "
            f"{step.contradicted} of {step.steps} odometry steps beyond their 99.9% bound; "
            f"inconsistency {step.inconsistency[0]:.1f} -> {step.inconsistency[1]:.1f} m^2; "
            f"the statements carry DCS Phi {step.relation_dcs:g} (the more consistent solve)"
        )


def run(args: argparse.Namespace) -> int:
    from hitl_slam.corrections_file import Apply, read_corrections
    from hitl_slam.errors import CorrectionRejected
    from hitl_slam.session import Session, StepRefused, moved_poses

    out = Path(args.output)
    check_map_output(out)
    refuse_overwriting_inputs(outputs_of(out), [args.map, args.corrections], args.force)
    session_path = None if args.session is None else Path(args.session)
    if session_path is not None:
        if session_path.suffix.lower() != ".hitl":
            raise InputError(f"{session_path}: a session file must end in .hitl; rename it")
        if session_path.exists():
            raise InputError(
                f"{session_path}: already exists; `hitl-slam correct` starts a new session and "
                "never overwrites one: choose another name or delete the old file"
            )
    steps = read_corrections(args.corrections)
    t_start = time.perf_counter()
    the_map = load_map(args, args.map)
    rejected: list[tuple[int, str]] = []
    counts = {"applied": 0, "undo": 0, "redo": 0}

    def reject(line: int, name: str, reason: str) -> None:
        if not args.keep_going:
            raise InputError(
                f"{args.corrections}:{line}: {reason}; nothing was written (fix or delete the "
                "line, or pass --keep-going to skip it)"
            )
        rejected.append((line, reason))
        if not args.quiet:
            print(f"{line:>5}  {name:<14} {'rejected (listed below)':>24}")

    with Session.new(the_map) as session:
        if not args.quiet:
            print(
                f"{args.map}: {the_map.num_poses} poses, {the_map.num_points} points; "
                f"{len(steps)} steps in {args.corrections}"
            )
            print(
                f"{'line':>5}  {'step':<14} {'moved':>7} {'chi2 before':>16} "
                f"{'chi2 after':>16} {'ms':>9}"
            )
        for step in steps:
            before = session.poses
            name = step.drawn.mode.value if isinstance(step, Apply) else type(step).__name__.lower()
            try:
                result = with_progress(
                    f"line {step.line}: {name}", args.quiet, partial(session.run_step, step)
                )
            except CorrectionRejected as exc:
                reject(step.line, name, f"{name} correction rejected: {one_line(str(exc))}")
                continue
            except StepRefused as exc:
                reject(step.line, name, str(exc))
                continue
            counts["applied" if result.action == "apply" else result.action] += 1
            stats = result.entry.stats if result.action == "apply" else None
            chi2 = (
                f"{'-':>16} {'-':>16}"
                if stats is None
                else f"{stats.initial_chi2:>16.6f} {stats.final_chi2:>16.6f}"
            )
            moved, _ = moved_poses(before, session.poses)
            if not args.quiet:
                print(f"{step.line:>5}  {name:<14} {moved:>7} {chi2} {1e3 * result.time_s:>9.2f}")
        if args.align:
            _align_session(args, session)
        _write_correct_outputs(args, session, out, session_path)
    if rejected and not args.quiet:
        print(f"rejected ({len(rejected)}):")
        for line, reason in rejected:
            print(f"  {args.corrections}:{line}: {reason}")
    applied = counts["applied"]
    done = f"{applied} correction{'' if applied == 1 else 's'} applied"
    if args.align:
        done += ", then aligned with the scans"
    if counts["undo"] or counts["redo"]:
        done += f", {counts['undo']} undone, {counts['redo']} redone"
    if rejected:
        lines = ", ".join(str(line) for line, _ in rejected)
        done += f", {len(rejected)} rejected (line{'s' if len(rejected) > 1 else ''} {lines})"
    written = f"wrote {out}" + ("" if session_path is None else f" and {session_path}")
    print(f"{done} in {time.perf_counter() - t_start:.2f} s; {written}")
    return 0


def _write_correct_outputs(
    args: argparse.Namespace, session: Session, out: Path, session_path: Path | None
) -> None:
    """OUT (and its .yaml) and the new session file, all or none: OUT is prepared, the session
    file created, then OUT renamed into place; if that fails the session file is removed."""
    from hitl_slam.io.atomic import atomic_outputs

    created = False
    try:
        with atomic_outputs():
            with_progress("writing", args.quiet, lambda: session.save(out))
            if session_path is not None:
                session.write_journal(session_path)
                created = True
    except BaseException as exc:
        if created and session_path is not None:
            try:
                os.unlink(session_path)
            except OSError as gone:
                exc.add_note(f"{session_path} could not be removed ({gone.strerror}): delete it")
        raise
