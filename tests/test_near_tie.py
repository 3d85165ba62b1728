"""A near-tie snap read again on the next line (docs/ALGORITHM.md §I.18).

A stroke drawn between two dense lines of nearly equal score (the snap of §I.1) says little about
which of them it meant. Where the reading on the nearer one contradicts the person's earlier
corrections (one of them, or the new one, would yield: §I.8), the drawing is read again with the
segment on the other line, and a reading that contradicts none is kept with a note.

Replayed from the full evaluation (Belgioioso, Kuemmerle et al. 2009 via Radish; bend, the
careful person with 15 cm endpoint noise, seed 0): its first eight drawings, the eighth read
again. The tie itself comes from the data, not from a constructed world.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hitl_slam.config import Config
from hitl_slam.corrections import Correction, Interpretation
from hitl_slam.corrections_file import Apply, read_corrections
from hitl_slam.errors import CorrectionRejected
from hitl_slam.evaluation import LASER
from hitl_slam.full_evaluation import damaged_scenario
from hitl_slam.map import Map
from hitl_slam.pipeline import apply_correction
from hitl_slam.session import Session

DATA = Path(__file__).parent / "data"
REREAD = "read on the next line"
CONTRADICTS = ("yield", "holds only in part")

pytestmark = pytest.mark.skipif(
    not (LASER / "belgioioso-corrected.log.gz").is_file(),
    reason="needs ../shared/datasets/laser beside the repository",
)


def test_a_near_tie_that_contradicts_earlier_corrections_is_read_on_the_next_line() -> None:
    seen: list[dict[str, Any]] = []

    def apply(
        map: Map,
        poses: np.ndarray,
        drawn: Correction,
        active: Sequence[Interpretation],
        config: Config,
    ) -> Any:
        result = apply_correction(map, poses, drawn, active, config)
        notes = result.interpretation.notes
        if not seen and any(REREAD in n for n in notes):
            # The same drawing on the same map without the second reading.
            first = apply_correction(
                map, poses, drawn, active, dataclasses.replace(config, near_tie_reading=False)
            )
            seen.append({"kept": result, "first": first, "active": len(active)})
        return result

    # The run's drawings up to the first read again, replayed on the same damaged map.
    scenario, _ = damaged_scenario("Belgioioso", "bend", 0.15, seed=0)
    drawings = read_corrections(DATA / "belgioioso-bend-15cm-seed0.jsonl")
    with Session.new(scenario.map, applier=apply) as session:
        for step in drawings:
            assert isinstance(step, Apply)
            try:
                session.apply(step.drawn)
            except CorrectionRejected:
                continue
    assert seen, f"no drawing was read again in {len(drawings)} drawings"
    kept, first = seen[0]["kept"], seen[0]["first"]
    note = next(n for n in kept.interpretation.notes if REREAD in n)
    # The first reading contradicted earlier corrections, and its note says so; the one kept
    # contradicts none, and it selected other observations for the moved segment.
    assert any(w in n for n in first.interpretation.notes for w in CONTRADICTS), first
    assert not any(
        w in n for n in kept.interpretation.notes for w in CONTRADICTS if n is not note
    ), kept.interpretation.notes
    h0, h1 = first.interpretation, kept.interpretation
    assert not (np.array_equal(h0.s_a, h1.s_a) and np.array_equal(h0.s_b, h1.s_b))
    assert seen[0]["active"] >= 1
