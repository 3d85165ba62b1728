"""The variant generators of benches/frontend_testbed.py on the first few hundred scans of the
public logs (no front end run): each variant changes what it says and nothing else."""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
LASER = ROOT.parent / "shared" / "datasets" / "laser"
pytestmark = pytest.mark.skipif(
    not (LASER / "intel.clf.bz2").is_file(), reason=f"public logs not found in {LASER}"
)
sys.path.insert(0, str(ROOT / "benches"))

import frontend_testbed as bed  # noqa: E402
from hitl_slam.sim.odometry import relative_motions  # noqa: E402

SCANS = 300


@pytest.fixture(scope="module")
def fr079() -> Any:
    return bed.base_map("fr079", SCANS)


def _ranges(points: Any) -> Any:
    return np.hypot(points[:, 0], points[:, 1])


def test_every_k_keeps_those_scans_untouched(fr079: Any) -> None:
    base, _, _ = fr079
    assert base.timestamps is not None
    for k in (2, 3, 5):
        out, keep, _ = bed.make_variant(base, f"every{k}")
        assert keep.tolist() == list(range(0, SCANS, k))
        assert np.array_equal(out.poses, base.poses[keep])
        assert out.timestamps is not None
        assert np.array_equal(out.timestamps, base.timestamps[keep])
        for i, j in enumerate(keep.tolist()):
            mine = out.points[out.offsets[i] : out.offsets[i + 1]]
            assert np.array_equal(mine, base.points[base.offsets[j] : base.offsets[j + 1]])


def test_a_combination_applies_its_parts_left_to_right(fr079: Any) -> None:
    base, _, _ = fr079
    out, keep, _ = bed.make_variant(base, "every3+bias3")
    thinned, kept, _ = bed.make_variant(base, "every3")
    biased, inner, _ = bed.make_variant(thinned, "bias3")
    assert keep.tolist() == kept[inner].tolist() == list(range(0, SCANS, 3))
    np.testing.assert_array_equal(out.poses, biased.poses)
    np.testing.assert_array_equal(out.points, thinned.points)
    assert not np.allclose(out.poses, base.poses[keep])
    assert bed._names("every3+bias3,raw", list(bed.VARIANTS), "variant") == ["every3+bias3", "raw"]
    with pytest.raises(SystemExit, match="unknown variant"):
        bed._names("every3+nonsense", list(bed.VARIANTS), "variant")


def test_heading_bias_and_scale_change_only_the_odometry_steps(fr079: Any) -> None:
    base, _, _ = fr079
    z = relative_motions(base.poses)
    dist = np.hypot(z[:, 0], z[:, 1])
    for variant, rate in (("bias1", 1.0), ("bias3", 3.0)):
        out, _, _ = bed.make_variant(base, variant)
        w = relative_motions(out.poses)
        np.testing.assert_allclose(w[:, :2], z[:, :2], atol=1e-9)
        turn = np.mod(w[:, 2] - z[:, 2] + math.pi, 2 * math.pi) - math.pi
        np.testing.assert_allclose(turn, math.radians(rate) * dist, atol=1e-9)
        assert np.array_equal(out.points, base.points)
    out, _, _ = bed.make_variant(base, "scale3")
    w = relative_motions(out.poses)
    np.testing.assert_allclose(w[:, :2], 1.03 * z[:, :2], atol=1e-9)
    np.testing.assert_allclose(w[:, 2], z[:, 2], atol=1e-9)


def test_short_narrow_float32_and_noise_move_points_along_their_beams(fr079: Any) -> None:
    base, _, _ = fr079
    r = _ranges(base.points)
    bearing = np.arctan2(base.points[:, 1], base.points[:, 0])
    out, _, notes = bed.make_variant(base, "short8m-180deg")
    assert _ranges(out.points).max() <= 8.0
    assert notes["points_dropped_range"] == int((r > 8.0).sum()) > 0
    assert out.num_points == base.num_points - notes["points_dropped_range"]
    assert out.num_poses == base.num_poses
    assert np.array_equal(out.poses, base.poses)
    for variant in ("float32", "noise5mm-s0", "noise5mm-s3"):
        out, _, _ = bed.make_variant(base, variant)
        assert out.offsets.tolist() == base.offsets.tolist()
        np.testing.assert_allclose(np.arctan2(out.points[:, 1], out.points[:, 0]), bearing)
        moved = _ranges(out.points) - r
        if variant == "float32":
            np.testing.assert_allclose(
                _ranges(out.points), r.astype(np.float32).astype(np.float64), rtol=1e-12
            )
            assert 0 < np.abs(moved).max() < 1e-5
        else:
            assert 0.0045 < moved.std() < 0.0055
            assert abs(moved.mean()) < 3e-4
    a, _, _ = bed.make_variant(base, "noise5mm-s1")
    b, _, _ = bed.make_variant(base, "noise5mm-s1")
    c, _, _ = bed.make_variant(base, "noise5mm-s2")
    assert np.array_equal(a.points, b.points)
    assert not np.array_equal(a.points, c.points)


def test_made_raw_is_the_damage_model_on_the_corrected_poses() -> None:
    base, truth, _ = bed.base_map("orebro", None)
    again, _, _ = bed.base_map("orebro", None)
    assert truth is not None
    assert base.num_poses == truth.shape[0] == 237
    assert np.array_equal(base.poses, again.poses)  # a fixed seed
    assert np.array_equal(base.poses[0], truth[0])
    assert np.abs(base.poses[1:, :2] - truth[1:, :2]).max() > 1.0  # noticeably damaged


def test_relations_of_a_thinned_log_are_those_between_kept_scans() -> None:
    from hitl_slam.io.relations import nearest_scans, read_relations

    base, _, whole = bed.base_map("intel", 1500)
    relations = read_relations(LASER / "intel.relations")
    full = nearest_scans(relations, whole)
    out, keep, _ = bed.make_variant(base, "every2")
    assert out.timestamps is not None
    subset, rows, pairs = bed._relations_for(relations, whole, keep, out.timestamps)
    assert len(subset) == rows.size == pairs.shape[0] > 0
    expected = [
        int(row)
        for row, (a, b) in zip(full.rows, full.pairs, strict=True)
        if a % 2 == 0 and b % 2 == 0 and a < 1500 and b < 1500
    ]
    assert rows.tolist() == expected
    assert np.array_equal(keep[pairs], full.pairs[np.searchsorted(full.rows, rows)])


def test_a_bag_of_a_log_reads_back_as_the_log(tmp_path: Path) -> None:
    pytest.importorskip("rosbags")
    from hitl_slam.io.maps import load_map

    base, _, _ = bed.base_map("fr079", 60)
    for kind in ("ros1", "sqlite3"):
        info = bed.write_log_bag("fr079", kind, tmp_path, 60)
        assert not info["restamped"]
        back = load_map(info["path"])
        assert back.timestamps is not None
        assert base.timestamps is not None
        assert back.offsets.tolist() == base.offsets.tolist()
        np.testing.assert_allclose(back.points, base.points, atol=1e-5)
        np.testing.assert_allclose(back.poses, base.poses, atol=1e-12)
        np.testing.assert_allclose(back.timestamps, base.timestamps, atol=1e-6)


def test_the_optimum_diagnostic_finds_a_reference_bent_off_the_scan_matching_optimum() -> None:
    from hitl_slam.geometry import chain_steps, integrate
    from hitl_slam.slam import slam

    base, truth, _ = bed.base_map("seattle", 120)
    assert truth is not None
    own = slam(bed._subset(base, np.arange(base.num_poses, dtype=np.int64), truth)).map
    # The front end's own poses sit at (near) the optimum; the same poses with one step turned
    # by 3 degrees in the middle do not.
    at = bed._reference_at_the_optimum(own, own.poses)
    steps = chain_steps(own.poses)
    steps[60, 2] += math.radians(3.0)
    off = bed._reference_at_the_optimum(own, integrate(own.poses[0], steps))
    assert at["optimum_steps_matched"] >= 110
    assert at["optimum_ate"] < 0.05, at
    assert off["optimum_ate"] > 2.0 * at["optimum_ate"] + 0.05, (at, off)
