"""`hitl-slam evaluate --full`: the harder evaluation of issue 11, kept as a benchmark.

Every map (the six corrected real logs in ../shared/datasets/laser and the generated worlds) is
damaged by each of the issue's fault models (:data:`hitl_slam.sim.fault_models.FULL_FAULTS`: a
large heading jump, slow drift, a bent corridor, three copies from two jumps; ``slip`` and
``scale`` on request) and repaired by a
:class:`~hitl_slam.sim.careful.CarefulPerson` drawing true statements with 5 cm and with 15 cm
endpoint noise, one correction at a time on the current map. Every drawing is recorded: accepted or
refused (and why), and the map's ATE, mean wall-angle error and inconsistency before and after.
Nothing here is tuned to a map: the faults' places, signs and sizes and the person's drawings are
drawn from the seed.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import time
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from hitl_slam.config import DEFAULT, Config
from hitl_slam.errors import CorrectionRejected, InputError
from hitl_slam.evaluation import LASER, _nanmean

if TYPE_CHECKING:
    from hitl_slam.corrections import Interpretation
    from hitl_slam.session import Applier, Session
    from hitl_slam.sim.careful import CarefulPerson, DrawingStyle
    from hitl_slam.sim.human import Inconsistency, Visit
    from hitl_slam.sim.scenario import Scenario

    ApplierFactory = Callable[[Scenario, CarefulPerson], Applier]
    """Makes the applier of one run from its damaged scenario and its person."""

__all__ = [
    "FULL_MAPS",
    "HALLS",
    "MAP_NAMES",
    "Drawing",
    "Run",
    "damaged_scenario",
    "full_report",
    "run_full",
    "runs_json",
    "summary",
    "targets_met",
]


REAL_LOGS = (
    ("intel-corrected.log.gz", "Intel lab"),
    ("freiburg-079-corrected.log.gz", "Freiburg 079"),
    ("seattle-corrected.log.gz", "Seattle"),
    ("orebro-corrected.log.gz", "Orebro"),
    ("belgioioso-corrected.log.gz", "Belgioioso"),
    ("edmonton-corrected.log.gz", "Edmonton"),
)
GENERATED = ("lost poses room", "parallel corridors", "campus")
FULL_MAPS = tuple(label for _, label in REAL_LOGS) + GENERATED
HALLS = ("hall",)
"""Maps run only when named (``--maps hall``): a large hall whose only long walls are its outer
ones (``hitl_slam.sim.hall_world``, issue 42), not yet part of the default set."""
MAP_NAMES = FULL_MAPS + HALLS
NOISES_M = (0.05, 0.15)
WORSE = 1.05
"""An accepted correction made its map worse when ATE or mean wall-angle error grew by more."""
NOISE_FLOOR = (0.02, 0.2)
"""[m], [deg] Changes of ATE and mean wall-angle error below these are within what the odometry
noise and the pseudo ground truth resolve; reported beside the strict 5% count, not instead."""


GUARDS = {
    "colocation guard (chi2, §I.3)": "positions along the wall contradict the odometry",
    "colocation consistency (scans, §I.13)": "more consistent with the two passes on one line",
    "consistency guard: passes nearest the drawings (§I.6)": "the passes kept first",
    "consistency guard: refused (§I.6)": "would contradict the robot's own measurements",
    "unchecked steps: robust odometry solve kept (§I.12)": "could not be checked by the scans",
    "near tie: read on the next line (§I.18)": "read on the next line",
}
"""Each guard that can change or refuse a correction, and the words of the note (or refusal) it
leaves when it does: a correction's notes say which guards acted on it."""


def _guards(texts: Sequence[str]) -> tuple[str, ...]:
    return tuple(name for name, words in GUARDS.items() if any(words in t for t in texts))


@dataclass(frozen=True)
class Drawing:
    """One drawing of the careful person and what it did to the map."""

    mode: str
    accepted: bool
    reason: str  # why it was refused ('' if accepted)
    ate: tuple[float, float]  # before, after [m]
    angle: tuple[float, float]  # mean wall-angle error before, after [deg]
    inconsistency: tuple[float, float]  # before, after [m^2]
    time_s: float
    meant: bool | None = None  # accepted: each segment selected poses of the pass it was drawn on
    guards: tuple[str, ...] = ()  # the guards that changed it (:data:`GUARDS`, by their notes)

    @property
    def worse(self) -> bool:
        """Accepted and ATE or the angle error grew by more than 5%."""
        return self.accepted and (
            self.ate[1] > WORSE * self.ate[0] or self.angle[1] > WORSE * self.angle[0]
        )

    @property
    def worse_beyond_noise(self) -> bool:
        """:attr:`worse`, and by more than :data:`NOISE_FLOOR` too."""
        return self.worse and (
            self.ate[1] > self.ate[0] + NOISE_FLOOR[0]
            or self.angle[1] > self.angle[0] + NOISE_FLOOR[1]
        )


@dataclass(frozen=True)
class Run:
    """One map under one fault model, repaired with one endpoint noise."""

    map: str
    fault: str
    noise_m: float
    poses: int
    drawings: tuple[Drawing, ...]
    angle: tuple[float, float]
    spacing: tuple[float, float]
    ate: tuple[float, float]
    inconsistency: tuple[float, float]
    inconsistency_truth: float
    finished: bool
    time_s: float
    faults: str = ""
    extra: dict[str, float] = field(default_factory=dict)
    # the person's last step: the map aligned with its scans (docs/ALGORITHM.md §I.11): ""
    # (not tried), "applied (Phi <the statements' Phi in the solve kept>)", or "refused: <why>";
    # and ATE, angle, spacing and inconsistency
    # before it (after the last drawing)
    alignment: str = ""
    before_alignment: tuple[float, float, float, float] | None = None

    @property
    def accepted(self) -> int:
        return sum(d.accepted for d in self.drawings)

    @property
    def achieved_fraction(self) -> float:
        """``(before - after) / (before - truth)``; NaN when the damage left the inconsistency at
        or below the truth's."""
        gain = self.inconsistency[0] - self.inconsistency_truth
        return (self.inconsistency[0] - self.inconsistency[1]) / gain if gain > 0 else math.nan


def _base_scenario(label: str, seed: int) -> object:
    """The map ``label`` with its truth, walls and scoring pairs, before any damage."""
    from hitl_slam.evaluation import real_log_scenario
    from hitl_slam.sim import campus, hall, lost_poses_room, parallel_corridors

    for file, name in REAL_LOGS:
        if name == label:
            path = LASER / file
            if not path.is_file():
                raise InputError(f"{path}: missing; the full evaluation needs ../shared beside it")
            return real_log_scenario(path, name=label, seed=seed, faults=lambda _n: [])
    builders: dict[str, Callable[[int], object]] = {
        "lost poses room": lambda s: lost_poses_room(s, drift_deg_per_m=0.0),
        "parallel corridors": lambda s: parallel_corridors(s, heading_jump_deg=0.0),
        "campus": lambda s: campus(s, heading_jump_deg=0.0, bend_deg_per_m=0.0),
        "hall": lambda s: hall(s, layout_seed=s, heading_jump_deg=0.0),
    }
    if label not in builders:
        raise InputError(f"unknown map {label!r}; the maps are: {', '.join(MAP_NAMES)}")
    return builders[label](seed)


def _reason(message: str) -> str:
    """A refusal message without its figures, to count refusals by kind."""
    text = re.sub(r"\([^)]*\)", "", message.split(";")[0])
    text = re.sub(r"-?\d+(\.\d+)?(e-?\d+)?", "#", text)
    return " ".join(text.split())


def _describe(faults: Sequence[object]) -> str:
    from hitl_slam.sim.odometry import HeadingJump, ScaleError, Slip

    parts = []
    for f in faults:
        if isinstance(f, HeadingJump):
            parts.append(f"jump {math.degrees(f.angle):+.1f} deg at pose {f.pose}")
        elif isinstance(f, Slip):
            parts.append(f"slip ({f.dx:+.2f}, {f.dy:+.2f}) m at pose {f.pose}")
        elif isinstance(f, ScaleError):
            parts.append(f"scale x{f.factor:.3f} over poses {f.start}-{f.stop}")
        else:
            parts.append(
                f"drift {math.degrees(f.rate):+.3f} deg/m over poses {f.start}-{f.stop}"  # type: ignore[attr-defined]
            )
    return "; ".join(parts)


def _selected_meant(h: Interpretation, issue: Inconsistency | None) -> bool | None:
    """Whether interpretation ``h`` kept, for each segment, poses of the pass the person drew
    it on (either order); None when the person's intent is unknown."""
    if issue is None:
        return None
    a, b = issue.a, issue.b
    xa, xb = h.x_a, h.x_b

    def on(x: np.ndarray, v: Visit) -> bool:
        return bool(np.any((x >= v.first) & (x <= v.last)))

    return (on(xa, a) and on(xb, b)) or (on(xa, b) and on(xb, a))


def damaged_scenario(
    label: str, fault: str, noise_m: float, seed: int
) -> tuple[Scenario, np.random.Generator]:
    """Map ``label`` damaged by fault model ``fault`` as the run of :func:`evaluate_run` with
    endpoint noise ``noise_m`` at ``seed`` damages it, and the random stream of that run's
    person (tests replay a run's drawings on the same damaged map from here)."""
    from hitl_slam.sim.fault_models import FAULT_MODELS, damaged
    from hitl_slam.sim.scenario import Scenario

    if fault not in FAULT_MODELS:
        raise InputError(f"unknown fault model {fault!r}; they are: {', '.join(FAULT_MODELS)}")
    # One stream per (map, fault, noise), all from the seed: nothing depends on the run order.
    key = [seed, MAP_NAMES.index(label), list(FAULT_MODELS).index(fault), int(noise_m * 1000)]
    fault_rng, odo_rng, person_rng = (
        np.random.default_rng(s) for s in np.random.SeedSequence(key).spawn(3)
    )
    base = _base_scenario(label, seed)
    assert isinstance(base, Scenario)
    faults = FAULT_MODELS[fault](base.truth, fault_rng)
    scenario = damaged(base, faults, int(odo_rng.integers(2**31)), name=f"{label} ({fault})")
    return scenario, person_rng


def evaluate_run(
    label: str,
    fault: str,
    noise_m: float,
    *,
    seed: int = 0,
    max_corrections: int = 40,
    config: Config = DEFAULT,
    on_end: Callable[[Scenario, Session], object] | None = None,
    align: bool = True,
    applier: ApplierFactory | None = None,
    person_style: DrawingStyle | None = None,
) -> Run:
    """Damages map ``label`` by fault model ``fault`` and lets a careful person with endpoint
    noise ``noise_m`` repair it, scoring every drawing. With ``align``, once they have drawn
    what they could (or ``max_corrections``), they align the map with its scans
    (:meth:`Session.align`), which is scored too. ``on_end(scenario, session)`` is called
    with the damaged scenario and the session at its last state, before the session closes.
    ``applier(scenario, person)``, if given, makes what computes each correction instead of
    :func:`hitl_slam.pipeline.apply_correction` (:func:`hitl_slam.sim.oracle.oracle_applier`:
    one that knows the truth). ``person_style``: how the person's strokes depart from what they
    see (:class:`~hitl_slam.sim.careful.DrawingStyle`; default: they do not)."""
    from hitl_slam.metrics import ate, inconsistency
    from hitl_slam.session import Session
    from hitl_slam.sim.careful import CarefulPerson, DrawingStyle

    start = time.perf_counter()
    scenario, person_rng = damaged_scenario(label, fault, noise_m, seed)
    m = scenario.map
    truth = scenario.truth

    def angle(poses: np.ndarray) -> float:
        return _nanmean(scenario.errors(poses).angular)

    def score(poses: np.ndarray, like: object = None) -> tuple[float, float, object]:
        inc = inconsistency(m, poses, config, like=like)  # type: ignore[arg-type]
        return float(ate(poses, truth, align=True)), angle(poses), inc

    person = CarefulPerson(
        scenario,
        person_rng,
        endpoint_noise=noise_m,
        config=config,
        style=person_style or DrawingStyle(),
    )
    session = Session.new(
        m, config=config, applier=None if applier is None else applier(scenario, person)
    )
    drawings: list[Drawing] = []
    alignment, before_alignment = "", None
    poses = np.array(session.poses)
    ate0, ang0, inc0 = score(poses)
    first = (ate0, ang0, inc0)
    finished = False
    try:
        while sum(d.accepted for d in drawings) < max_corrections:
            drawn = person.next_correction(poses)
            if drawn is None:
                finished = True
                break
            t0 = time.perf_counter()
            try:
                session.apply(drawn)
            except CorrectionRejected as err:
                person.rejected(drawn)
                drawings.append(
                    Drawing(
                        drawn.mode.value,
                        False,
                        str(err),
                        (ate0, ate0),
                        (ang0, ang0),
                        (inc0.total_m2, inc0.total_m2),  # type: ignore[attr-defined]
                        time.perf_counter() - t0,
                        guards=_guards([str(err)]),
                    )
                )
                continue
            spent = time.perf_counter() - t0
            meant = _selected_meant(session.active[-1], person.last)
            poses = np.array(session.poses)
            ate1, ang1, inc1 = score(poses, like=first[2])
            drawings.append(
                Drawing(
                    drawn.mode.value,
                    True,
                    "",
                    (ate0, ate1),
                    (ang0, ang1),
                    (inc0.total_m2, inc1.total_m2),  # type: ignore[attr-defined]
                    spent,
                    meant,
                    _guards(session.active[-1].notes),
                )
            )
            ate0, ang0, inc0 = ate1, ang1, inc1
        if align:
            before_alignment = (
                ate0,
                ang0,
                _nanmean(scenario.errors(poses).translational),
                inc0.total_m2,  # type: ignore[attr-defined]
            )
            try:
                step = session.align()
            except InputError as err:
                alignment = f"refused: {err}"
            else:
                alignment = f"applied (Phi {step.relation_dcs:g})"
                poses = np.array(session.poses)
                ate0, ang0, inc0 = score(poses, like=first[2])
        if on_end is not None:
            on_end(scenario, session)
    finally:
        session.close()
    inc_truth = inconsistency(m, truth, config, like=first[2])  # type: ignore[arg-type]
    e0, e1 = scenario.errors(m.poses), scenario.errors(poses)
    return Run(
        map=label,
        fault=fault,
        noise_m=noise_m,
        poses=m.num_poses,
        drawings=tuple(drawings),
        angle=(first[1], ang0),
        spacing=(_nanmean(e0.translational), _nanmean(e1.translational)),
        ate=(first[0], ate0),
        inconsistency=(first[2].total_m2, inc0.total_m2),  # type: ignore[attr-defined]
        inconsistency_truth=inc_truth.total_m2,
        finished=finished,
        time_s=time.perf_counter() - start,
        faults=_describe(list(scenario.faults)),
        alignment=alignment,
        before_alignment=before_alignment,
    )


def _run_one(
    args: tuple[str, str, float, int, bool, ApplierFactory | None, DrawingStyle | None],
) -> Run:
    label, fault, noise, seed, align, applier, style = args
    return evaluate_run(
        label, fault, noise, seed=seed, align=align, applier=applier, person_style=style
    )


def run_full(
    *,
    seed: int = 0,
    maps: Sequence[str] = FULL_MAPS,
    faults: Sequence[str] | None = None,
    noises: Sequence[float] = NOISES_M,
    jobs: int = 1,
    log: Callable[[Run], None] = lambda _r: None,
    align: bool = True,
    applier: ApplierFactory | None = None,
    person_style: DrawingStyle | None = None,
) -> list[Run]:
    """Every (map, fault model, noise) run, in that order (``jobs`` processes at once), each
    with ``applier`` and ``person_style`` as :func:`evaluate_run` (with ``jobs`` > 1 the
    applier must pickle: a module-level function, or a ``functools.partial`` of one)."""
    from hitl_slam.sim.fault_models import FULL_FAULTS

    for label in maps:
        if label not in MAP_NAMES:
            raise InputError(f"unknown map {label!r}; the maps are: {', '.join(MAP_NAMES)}")
    work = [
        (label, fault, noise, seed, align, applier, person_style)
        for label in maps
        for fault in (faults or FULL_FAULTS)
        for noise in noises
    ]
    runs: list[Run] = []
    if jobs <= 1:
        for w in work:
            runs.append(_run_one(w))
            log(runs[-1])
        return runs
    with ProcessPoolExecutor(max_workers=jobs) as pool:
        for r in pool.map(_run_one, work):
            runs.append(r)
            log(r)
    return runs


def _guard_table(runs: Sequence[Run]) -> list[str]:
    """How often each guard changed or refused a drawing, over every run (by the notes it left);
    and how many accepted colocations paid for the colocation guard's second solve."""
    drawings = [d for r in runs for d in r.drawings]
    colocations = sum(d.accepted and d.mode == "colocation" for d in drawings)
    lines = [
        "How often each guard acted: changed an accepted correction (its note says so) or "
        f"refused a drawing. Every accepted colocation ({colocations} of "
        f"{sum(d.accepted for d in drawings)}) was also solved as collinear for the colocation "
        "guard, whether or not it changed anything.",
        "",
        "| guard | accepted, changed by it | refused by it |",
        "|---|---|---|",
    ]
    for name in GUARDS:
        changed = sum(d.accepted and name in d.guards for d in drawings)
        refused = sum(not d.accepted and name in d.guards for d in drawings)
        lines.append(f"| {name} | {changed} | {refused} |")
    return lines


def summary(runs: Sequence[Run]) -> dict[str, float]:
    """The acceptance figures over ``runs``."""
    drawings = [d for r in runs for d in r.drawings]
    accepted = [d for d in drawings if d.accepted]
    return {
        "drawings": float(len(drawings)),
        "accepted": float(len(accepted)),
        "accepted_share": len(accepted) / len(drawings) if drawings else math.nan,
        "worse": float(sum(d.worse for d in accepted)),
        "worse_beyond_noise": float(sum(d.worse_beyond_noise for d in accepted)),
        "meant": float(sum(d.meant is True for d in accepted)),
        "worse_beyond_noise_meant": float(
            sum(d.worse_beyond_noise and d.meant is True for d in accepted)
        ),
        "achieved": _nanmean(np.array([r.achieved_fraction for r in runs])),
        "angle_after": _nanmean(np.array([r.angle[1] for r in runs])),
        "spacing_after": _nanmean(np.array([r.spacing[1] for r in runs])),
        "angle_before": _nanmean(np.array([r.angle[0] for r in runs])),
        "spacing_before": _nanmean(np.array([r.spacing[0] for r in runs])),
    }


def targets_met(s: Mapping[str, float]) -> dict[str, bool]:
    """Which of the benchmark's targets the :func:`summary` ``s`` meets: ``accepted`` (at least
    95% of the drawings accepted), ``worse`` (none made its map worse), ``achieved`` (at least 80%
    of the achievable inconsistency reduction), ``angle`` (at most 1 degree after) and
    ``spacing`` (at most 3 cm after); a figure that is NaN meets nothing."""
    return {
        "accepted": s["accepted_share"] >= 0.95,
        "worse": s["worse"] == 0,
        "achieved": s["achieved"] >= 0.80,
        "angle": s["angle_after"] <= 1.0,
        "spacing": s["spacing_after"] <= 0.03,
    }


def _fmt_run(r: Run) -> str:
    return (
        f"| {r.map} | {r.fault} | {100 * r.noise_m:.0f} | {r.poses} | {len(r.drawings)} "
        f"| {r.accepted} | {sum(d.worse for d in r.drawings)} "
        f"| {sum(d.worse_beyond_noise for d in r.drawings)} "
        f"| {r.ate[0]:.3f} | {r.ate[1]:.3f} | {r.angle[0]:.2f} | {r.angle[1]:.2f} "
        f"| {r.spacing[0]:.3f} | {r.spacing[1]:.3f} "
        f"| {r.inconsistency[0]:.1f} | {r.inconsistency[1]:.1f} | {r.inconsistency_truth:.1f} "
        f"| {100 * r.achieved_fraction:.0f}% | {r.alignment.split(':')[0] or '-'} "
        f"| {r.time_s:.0f} |"
    )


def _alignment_worse(r: Run) -> bool:
    """The alignment was applied and raised ATE or the mean wall-angle error by over 5%."""
    if not r.alignment.startswith("applied") or r.before_alignment is None:
        return False
    ate0, ang0 = r.before_alignment[:2]
    return r.ate[1] > WORSE * ate0 or r.angle[1] > WORSE * ang0


def _refusals(runs: Sequence[Run]) -> dict[str, int]:
    """How many alignments each guard refused."""
    kinds = {  # the first that matches: the overruling message names loop closures too
        "contradict what you said": "overruling the statements (§I.16)",
        "loop closures": "with too few loop closures",
        "disagree with the odometry": "contradicting the odometry",
        "no more consistent": "no more consistent",
    }
    out: dict[str, int] = {}
    for r in runs:
        if r.alignment.startswith("refused"):
            kind = next((v for k, v in kinds.items() if k in r.alignment), "other")
            out[kind] = out.get(kind, 0) + 1
    return out


def _alignment_lines(runs: Sequence[Run]) -> list[str]:
    tried = [r for r in runs if r.alignment]
    if not tried:
        return []
    applied = [r for r in tried if r.alignment.startswith("applied")]
    worse = [r for r in applied if _alignment_worse(r)]
    firm = [r for r in applied if r.alignment == f"applied (Phi {DEFAULT.relation_dcs:g})"]
    lines = [
        "## Alignment with the scans",
        "",
        f"Applied in {len(applied)} of {len(tried)} runs; refused in the others by a guard "
        "(docs/ALGORITHM.md §I.11, §I.16), the run's section below says which: "
        + ", ".join(f"{v} {k}" for k, v in sorted(_refusals(tried).items()))
        + f". It raised ATE or the mean wall-angle error by more than 5% in {len(worse)} of the "
        f"{len(applied)}. Of the two solves it tries (the statements yielding to the scans, "
        f"Phi {DEFAULT.align_relation_dcs:g}, or firm, Phi {DEFAULT.relation_dcs:g}) it kept the "
        f"firm one, the more consistent there, in {len(firm)}. Before: after the last drawing; "
        "after: after the alignment (the runs table's 'out').",
        "",
        "| map | fault | noise (cm) | alignment | ATE (m) | angle (deg) | spacing (m) "
        "| inconsistency (m^2) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in tried:
        assert r.before_alignment is not None
        a, g, sp, inc = r.before_alignment
        what = r.alignment.split(":")[0] + (", **worse**" if _alignment_worse(r) else "")
        lines.append(
            f"| {r.map} | {r.fault} | {100 * r.noise_m:.0f} | {what} "
            f"| {a:.3f} -> {r.ate[1]:.3f} | {g:.2f} -> {r.angle[1]:.2f} "
            f"| {sp:.3f} -> {r.spacing[1]:.3f} | {inc:.1f} -> {r.inconsistency[1]:.1f} |"
        )
    return [*lines, ""]


def runs_json(runs: Sequence[Run]) -> str:
    """Every run and drawing as JSON (the benchmark's machine-readable record)."""
    return json.dumps([dataclasses.asdict(r) for r in runs], indent=1)


def full_report(runs: Sequence[Run], provenance: str) -> str:
    """The Markdown report: targets, the table per run, refusals by reason, every drawing."""
    s = summary(runs)
    ok = targets_met(s)

    def met(flag: bool) -> str:
        return "yes" if flag else "**no**"

    lines = [
        "# hitl-slam full evaluation (issue 11)",
        "",
        provenance,
        "",
        "Each map is damaged by each fault model of the run (`hitl_slam.sim.fault_models`: `jump`",
        "one 30-degree heading jump in the middle 40% of the run; `drift` 15 degrees of heading",
        "drift spread over the whole run; `bend` 10 degrees along the straightest stretch; `laps`",
        "two jumps of 8-15 degrees, three copies of what is seen throughout; on request `slip`,",
        "one step's translation 0.5-1.5 m off, and `scale`, every distance 3-6% off), with",
        "1% / 2% / 0.1 deg/m odometry noise besides, then repaired by a careful person",
        "(`hitl_slam.sim.careful.CarefulPerson`) who draws only true statements on the copies",
        "they can see, in random direction, with 5 cm or 15 cm endpoint noise, one correction at",
        "a time on the current map, each committed as drawn. Once they have drawn what they",
        "could (or 40 corrections), they align the map with its scans (`Session.align`,",
        "docs/ALGORITHM.md §I.11) unless the run says otherwise; 'out' is after that step.",
        "Places, signs and sizes of the faults and every drawing come from the seed.",
        "",
        "Angle and spacing errors are the paper's Table 1 measures: on a real log, pairs of long",
        "walls parallel or perpendicular (within 1 degree) on its corrected poses, and, for the",
        "spacing, parallel walls that face each other at least 0.5 m apart (a corridor's or a",
        "room's width, as the paper's; `hitl_slam.evaluation.real_log_scenario`); on a generated",
        "world, its known pairs. Dataset credits: README, 'Data credits'.",
        "",
        "## Targets",
        "",
        "| target | measured | met |",
        "|---|---|---|",
        f"| drawings accepted >= 95% | {100 * s['accepted_share']:.2f}% "
        f"({s['accepted']:.0f} of {s['drawings']:.0f}) | {met(ok['accepted'])} |",
        f"| accepted corrections raising ATE or mean wall-angle error > 5% = 0 "
        f"| {s['worse']:.0f} of {s['accepted']:.0f} ({s['worse_beyond_noise']:.0f} of them also "
        f"by more than {NOISE_FLOOR[0]:g} m / {NOISE_FLOOR[1]:g} deg) | {met(ok['worse'])} |",
        f"| mean inconsistency reduction >= 80% of the achievable | {100 * s['achieved']:.0f}% "
        f"| {met(ok['achieved'])} |",
        f"| mean corrected wall-angle error <= 1.0 deg | {s['angle_after']:.2f} deg "
        f"(before {s['angle_before']:.2f}) | {met(ok['angle'])} |",
        f"| mean corrected translational (spacing) error <= 0.03 m | {s['spacing_after']:.3f} m "
        f"(before {s['spacing_before']:.3f}) | {met(ok['spacing'])} |",
        "",
        f"Of the {s['accepted']:.0f} accepted corrections, {s['meant']:.0f} kept, for each "
        "segment, poses of the pass it was drawn on (the others selected a different pass of",
        f"the same wall); {s['worse_beyond_noise_meant']:.0f} of the "
        f"{s['worse_beyond_noise']:.0f} worse beyond the noise did.",
        "",
        *_guard_table(runs),
        "",
        "## Runs",
        "",
        "| map | fault | noise (cm) | poses | drawings | accepted | worse | worse beyond noise "
        "| ATE in (m) | ATE out | angle in (deg) | angle out | spacing in (m) | spacing out "
        "| inconsistency in (m^2) | out | truth | of achievable | alignment | time (s) |",
        "|" + "---|" * 20,
        *(_fmt_run(r) for r in runs),
        "",
        *_alignment_lines(runs),
        "## Refusals by reason",
        "",
    ]
    reasons: dict[str, int] = {}
    for r in runs:
        for d in r.drawings:
            if not d.accepted:
                reasons[_reason(d.reason)] = reasons.get(_reason(d.reason), 0) + 1
    if reasons:
        lines += ["| reason | count |", "|---|---|"]
        lines += [f"| {k} | {v} |" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1])]
    else:
        lines.append("None.")
    lines += ["", "## Every drawing", ""]
    for r in runs:
        lines += [
            f"### {r.map}, {r.fault}, {100 * r.noise_m:.0f} cm",
            "",
            f"Faults: {r.faults}. Finished: {'yes' if r.finished else 'no (correction limit)'}.",
            "",
            "| # | mode | outcome | ATE (m) | angle (deg) | inconsistency (m^2) | time (ms) |",
            "|---|---|---|---|---|---|---|",
        ]
        for k, d in enumerate(r.drawings, 1):
            outcome = (
                ("accepted, **worse**" if d.worse else "accepted")
                + (", another pass selected" if d.meant is False else "")
                if d.accepted
                else ("refused: " + d.reason.replace("|", "/"))
            )
            lines.append(
                f"| {k} | {d.mode} | {outcome} | {d.ate[0]:.3f} -> {d.ate[1]:.3f} "
                f"| {d.angle[0]:.2f} -> {d.angle[1]:.2f} "
                f"| {d.inconsistency[0]:.1f} -> {d.inconsistency[1]:.1f} | {1000 * d.time_s:.0f} |"
            )
        if r.alignment:
            lines += ["", f"Alignment with the scans: {r.alignment.replace('|', '/')}."]
        lines.append("")
    lines += [
        "Real logs: the Intel Research Lab, Freiburg building 079, Seattle, Orebro, Belgioioso",
        "and Edmonton corrected logs, via Radish (thanks to their authors: D. Haehnel,",
        "C. Stachniss, and the Freiburg SLAM benchmark of Kuemmerle et al. 2009; the corrected",
        "CARMEN versions from the acschaefer/ple repository). Their corrected poses serve as",
        "pseudo ground truth; walls are found in the corrected map by RANSAC.",
        "",
    ]
    return "\n".join(lines)
