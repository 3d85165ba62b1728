"""kill -9 trials of a session (issue 13): a child process creates a session and runs a plan of
steps (corrections, undo, redo, saves to .g2o and TUM .txt), printing "ack <k>" once step k has
returned; the parent kills it with SIGKILL at a random moment, reopens the session file and
checks that:

- every acknowledged step is in it and nothing else: the reopened poses and history equal a
  reference run of exactly the acknowledged steps, or of one more (the step in flight had been
  committed but not yet acknowledged), or the acknowledged ones plus that step's request marked
  interrupted (killed during its computation);
- nothing is half-written: the session file opens (integrity check and checksums), every saved
  output under its final name reads back, and the reopened session takes a new correction.

    python tests/kill_trials.py --trials 200      # `make kill-trials`
    python tests/kill_trials.py --trials 3        # the short run tests/test_kill_trials.py does

Prints one line per 20 trials and a summary, e.g. "200 trials, 0 lost acknowledged steps,
0 partial outputs"; exits 1 when any check failed.
"""

from __future__ import annotations

import argparse
import os
import random
import select
import signal
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

TESTS = Path(__file__).resolve().parent
sys.path.insert(0, str(TESTS))

import numpy as np  # noqa: E402

from hitl_slam.errors import InputError  # noqa: E402
from hitl_slam.session import EntryStatus, Session  # noqa: E402

Step = tuple[str, float]  # ("apply", seed) | ("undo", 0) | ("redo", 0) | ("save", k)
OUTPUTS = (".g2o", ".txt")


def plan(seed: int, length: int = 10) -> list[Step]:
    """A valid plan (never an undo or redo with nothing to undo or redo)."""
    rng = random.Random(seed)
    steps: list[Step] = []
    applied = undone = 0
    for k in range(length):
        choices = ["apply", "apply", "save"]
        if applied:
            choices.append("undo")
        if undone:
            choices.append("redo")
        action = rng.choice(choices)
        if action == "apply":
            steps.append(("apply", round(rng.uniform(0.1, 9.0), 3)))
            applied, undone = applied + 1, 0
        elif action == "undo":
            steps.append(("undo", 0.0))
            applied, undone = applied - 1, undone + 1
        elif action == "redo":
            steps.append(("redo", 0.0))
            applied, undone = applied + 1, undone - 1
        else:
            steps.append(("save", float(k)))
    return steps


def output_path(session_path: Path, k: int) -> Path:
    return session_path.with_name(f"out{k}{OUTPUTS[k % len(OUTPUTS)]}")


def run_step(session: Session, step: Step, path: Path | None) -> None:
    import test_session as t

    action, value = step
    if action == "apply":
        session.apply(t.drawing(value))
    elif action == "undo":
        session.undo()
    elif action == "redo":
        session.redo()
    elif path is not None:
        session.save(output_path(path, int(value)))


# -- the child ------------------------------------------------------------------------------------


def child(path: Path, seed: int) -> None:
    import test_session as t

    rng = random.Random(seed ^ 0x5EED)

    def applier(*args: Any) -> Any:
        time.sleep(rng.uniform(0.0, 0.01))  # a computation of a few milliseconds
        return t.fake_applier(*args)

    print("start", flush=True)
    session = Session.new(t.tiny_map(), path, applier=applier)
    print("ack 0", flush=True)
    for k, step in enumerate(plan(seed), 1):
        run_step(session, step, path)
        print(f"ack {k}", flush=True)
    session.close()
    print("done", flush=True)


# -- the parent -----------------------------------------------------------------------------------


State = tuple[np.ndarray, list[EntryStatus]]


def reference(seed: int) -> list[State]:
    """The state after 0, 1, ... steps of the plan, computed in memory."""
    import test_session as t

    session = Session.new(t.tiny_map(), applier=t.fake_applier)
    states = [(session.poses.copy(), [e.status for e in session.history])]
    for step in plan(seed):
        run_step(session, step, None)
        states.append((session.poses.copy(), [e.status for e in session.history]))
    return states


def same_state(a: State, b: State) -> bool:
    return a[0].tobytes() == b[0].tobytes() and a[1] == b[1]


@dataclass
class Tally:
    trials: int = 0
    lost: int = 0  # acknowledged steps missing, or a state matching no allowed one
    partial: int = 0  # a session file or an output under its final name that does not read
    in_flight_committed: int = 0  # the step in flight was in the file (allowed)
    in_flight_interrupted: int = 0  # its request was, without its outcome (allowed)
    never_created: int = 0  # killed before Session.new returned (allowed: no file at all)
    leftovers: int = 0  # temporary files left beside (reported, not counted as partial)
    leftover_sessions: int = 0  # ... of them, a session file being created (.s.hitl.*.tmp)
    failures: list[str] = field(default_factory=list)


def run_child(path: Path, seed: int, kill_after: float | None) -> tuple[int, float | None]:
    """Run the child; kill it ``kill_after`` seconds after it started its work (None: let it
    finish). Returns the last acknowledged step (-1: none) and, when it finished, the time its
    work took [s]."""
    process = subprocess.Popen(
        [sys.executable, __file__, "--child", str(path), "--seed", str(seed)],
        stdout=subprocess.PIPE,
    )
    assert process.stdout is not None
    acked, started = -1, None
    done: float | None = None
    buffer = b""
    deadline = time.monotonic() + 60
    try:
        while True:
            now = time.monotonic()
            if now > deadline:
                raise RuntimeError("the child hung")
            if started is not None and kill_after is not None and now >= started + kill_after:
                process.send_signal(signal.SIGKILL)
                break
            timeout = 0.05 if started is None or kill_after is None else started + kill_after - now
            ready, _, _ = select.select([process.stdout], [], [], max(0.0, min(timeout, 0.05)))
            if not ready:
                if process.poll() is not None:
                    break
                continue
            chunk = os.read(process.stdout.fileno(), 4096)
            if not chunk:
                break
            buffer += chunk
            *lines, buffer = buffer.split(b"\n")
            for line in lines:
                if line == b"start":
                    started = time.monotonic()
                elif line.startswith(b"ack "):
                    acked = int(line[4:])
                elif line == b"done" and started is not None:
                    done = time.monotonic() - started
    finally:
        process.kill()
        process.wait()
        # Acknowledgements printed before the kill landed, still in the pipe.
        rest = buffer + process.stdout.read()
        for line in rest.split(b"\n"):
            if line.startswith(b"ack "):
                acked = max(acked, int(line[4:]))
        process.stdout.close()
    return acked, done


def check_trial(directory: Path, seed: int, acked: int, refs: list[State], tally: Tally) -> None:
    path = directory / "s.hitl"
    steps = plan(seed)
    tally.trials += 1
    leftovers = [p for p in directory.iterdir() if p.name.endswith(".tmp")]
    tally.leftovers += len(leftovers)
    tally.leftover_sessions += sum(p.name.startswith(".s.hitl.") for p in leftovers)
    if not path.exists():
        if acked >= 0:
            tally.lost += 1
            tally.failures.append(f"seed {seed}: session acknowledged but no file")
        else:
            tally.never_created += 1
        return
    try:
        session = Session.open(path)
    except InputError as exc:
        tally.partial += 1
        tally.failures.append(f"seed {seed}: the session file does not open: {exc}")
        return
    with session:
        got = (session.poses.copy(), [e.status for e in session.history])
        base = max(acked, 0)
        allowed = [("acknowledged", refs[base])]
        if base + 1 < len(refs):
            allowed.append(("in flight, committed", refs[base + 1]))
            if steps[base][0] == "apply":
                interrupted = (refs[base][0], [*refs[base][1], EntryStatus.INTERRUPTED])
                allowed.append(("in flight, interrupted", interrupted))
        match = next((name for name, state in allowed if same_state(got, state)), None)
        if match is None:
            tally.lost += 1
            tally.failures.append(
                f"seed {seed}: {acked} steps acknowledged, the file holds another state "
                f"({len(got[1])} history entries)"
            )
        elif match == "in flight, committed":
            tally.in_flight_committed += 1
        elif match == "in flight, interrupted":
            tally.in_flight_interrupted += 1
        # Outputs: every acknowledged save is there and reads back; any other output under its
        # final name reads back too.
        from hitl_slam.io import load_graph

        for k, (action, value) in enumerate(steps, 1):
            if action != "save":
                continue
            out = output_path(path, int(value))
            if not out.exists():
                if k <= acked:
                    tally.lost += 1
                    tally.failures.append(f"seed {seed}: acknowledged save {out.name} missing")
                continue
            try:
                if out.suffix == ".g2o":
                    ok = load_graph(out).num_poses == session.input_map.num_poses
                else:
                    rows = np.loadtxt(out, ndmin=2)
                    ok = rows.shape == (session.input_map.num_poses, 8)
            except (InputError, ValueError, OSError) as exc:
                ok = False
                tally.failures.append(f"seed {seed}: {out.name} does not read: {exc}")
            if not ok:
                tally.partial += 1
                tally.failures.append(f"seed {seed}: {out.name} is incomplete")
        # The reopened session takes a new correction.
        import test_session as t

        session._applier = t.fake_applier
        try:
            session.apply(t.drawing(4.4))
        except Exception as exc:  # a trial reports every failure, whatever its kind
            tally.partial += 1
            tally.failures.append(f"seed {seed}: the reopened session refused a correction: {exc}")


def calibrate(seed: int) -> float:
    """How long the child's work takes, from "start" to its last step [s]."""
    with tempfile.TemporaryDirectory(prefix="kill-trials-") as directory:
        acked, span = run_child(Path(directory) / "s.hitl", seed, None)
        if span is None or acked != len(plan(seed)):
            raise RuntimeError(f"the child did not finish its plan (acknowledged {acked})")
        return span


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args(argv)
    if args.child is not None:
        child(args.child, args.seed)
        return 0
    rng = random.Random(args.seed)
    span = calibrate(args.seed)
    tally = Tally()
    acked_seen: dict[int, int] = {}
    t0 = time.monotonic()
    for trial in range(args.trials):
        seed = args.seed * 100_003 + trial
        refs = reference(seed)
        with tempfile.TemporaryDirectory(prefix="kill-trials-") as directory:
            kill_after = rng.uniform(0.0, span)
            acked, _ = run_child(Path(directory) / "s.hitl", seed, kill_after)
            acked_seen[acked] = acked_seen.get(acked, 0) + 1
            check_trial(Path(directory), seed, acked, refs, tally)
        if not args.quiet and (trial + 1) % 20 == 0:
            print(
                f"  {trial + 1} trials, {tally.lost} lost, {tally.partial} partial "
                f"({time.monotonic() - t0:.0f} s)",
                flush=True,
            )
    for failure in tally.failures:
        print("FAIL", failure)
    spread = ", ".join(f"{k}: {v}" for k, v in sorted(acked_seen.items()))
    print(
        f"{tally.trials} trials, {tally.lost} lost acknowledged steps, {tally.partial} partial "
        f"outputs (killed with the step in flight committed: {tally.in_flight_committed}, "
        f"interrupted: {tally.in_flight_interrupted}; before the session existed: "
        f"{tally.never_created}; temporary files left: {tally.leftovers}, of which "
        f"{tally.leftover_sessions} of a session being created; steps acknowledged "
        f"when killed -> trials: {spread})"
    )
    return 1 if tally.lost or tally.partial else 0


if __name__ == "__main__":
    sys.exit(main())
