"""Every tunable constant of the method in one documented object (docs/ALGORITHM.md), with units.

Pass a :class:`Config` (or use :data:`DEFAULT`) wherever behaviour depends on a constant; nothing
else in the package hard-codes these numbers.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any

from hitl_slam.errors import InputError

__all__ = ["DEFAULT", "Config"]


@dataclass(frozen=True)
class Config:
    """Constants of HitL-SLAM. Units in brackets.

    Motion model (docs/ALGORITHM.md §1.3), used when an edge has no usable covariance:
    ``sigma_t = max(sigma_t0, k_t |dt|)``, ``sigma_theta = max(sigma_theta0, k_theta |dtheta| +
    k_theta_t |dt|)``.

    Interpretation (§3): ``sigma_h`` the human's pointing accuracy (default for library callers),
    ``search_band * sigma_h`` how far from a drawn segment the wall it was meant for is searched
    (0: EM starts at the drawn line, as the paper), ``drawing_sigma * sigma_h`` how far from that
    wall a careful person's endpoints land (it weighs closeness against a line's support),
    candidate band ``r_c = candidate_band * sigma_h``, ``sigma_em`` sensor noise plus wall
    roughness, initial clutter mixing weight, EM stopping rule, ``min_points_per_pose`` (T_p),
    ``visit_gap`` (how far apart in pose index two runs of selected poses are separate visits).

    Factors (§4.3): ``sigma_f`` point-to-line weight, ``k1`` / ``k2`` weights of the relation
    residual R_p, ``average_points`` for the paper's RMS form of R_a/R_b.

    Inconsistency metric (§6.2): ``metric_surface_cells``, ``metric_min_stop`` and
    ``metric_grazing_deg`` are its robustness rules (a) and (b); the grid is ``grid_resolution``.

    Chosen defaults and why: sigma_f = 3 cm is the laser's range noise plus wall roughness, so a
    line stays on its own observations; K1 = 1e6 /m^2 and K2 = 1e7 /rad^2 make a human relation far
    stronger than any odometry edge (a person who says "same wall" means it) while per-point R_a/R_b
    keep the lines tied to the observations, so the relation holds between the observations and not
    just between the line variables.
    """

    # §1.3 motion model
    sigma_t0: float = 0.03  # [m]
    k_t: float = 0.05  # [m/m]
    sigma_theta0: float = 0.01  # [rad]
    k_theta: float = 0.05  # [rad/rad]
    k_theta_t: float = 0.01  # [rad/m]
    # §3 interpretation
    sigma_h: float = 0.10  # [m]
    candidate_band: float = 3.0  # [sigma_h]
    search_band: float = 5.0  # [sigma_h] 0 = no search
    drawing_sigma: float = 2.0  # [sigma_h]
    sigma_em: float = 0.03  # [m]
    clutter_weight: float = 0.5  # [1] initial pi
    em_tolerance_m: float = 1e-4  # [m]
    em_tolerance_rad: float = 1e-4  # [rad]
    em_max_iterations: int = 50
    min_points_per_pose: int = 8  # T_p
    visit_gap: int = 10  # [poses] a gap larger than this in selected poses starts a new visit
    # §4.3 factors
    sigma_f: float = 0.03  # [m]
    k1: float = 1e6  # [1/m^2]
    k2: float = 1e7  # [1/rad^2]
    average_points: bool = False
    # solver for corrections
    max_iterations: int = 50
    relative_tolerance: float = 1e-6
    absolute_tolerance: float = 1e-6
    # robust kernels in the joint solve, per edge class ("" for none), e.g. "odometry=cauchy:1"
    # (hitl_slam.solve.robust_pairs)
    robust: str = ""
    # contradicted relations (docs/ALGORITHM.md §I.8): each correction's relation R_p carries
    # dynamic covariance scaling with this Phi [chi2], so where corrections contradict one
    # another the odometry decides and the statement it contradicts yields instead of bending
    # the map. 1000 is about K1 sigma_f^2: a relation held off by more than ~3 cm (or, on its
    # angle row at K2, ~0.6 deg) starts to yield. 0 = off (every relation hard, as the paper);
    # a "relation=..." kernel in `robust` replaces it
    relation_dcs: float = 1000.0
    # colocation guard: the chi2 of the map's own measurements a colocation may cost above the
    # same correction solved as collinear before it is applied as collinear (0 = off; 3.84 is
    # chi2 with one degree of freedom at 95%: the along-the-wall part is one constraint)
    colocation_guard: float = 3.84
    # and where the chi2 lets the colocation stand, the one of the two solutions under which the
    # scans agree the better (the inconsistency metric, §6) is kept: where the chain between
    # the passes is loose (steps the scans could not check), the chi2 cannot contradict a
    # person's "same stretch", which they judge to a few decimetres (docs/ALGORITHM.md §I.13;
    # False: chi2 alone)
    colocation_consistency: bool = True
    # odometry check: an odometry step whose two scans turn this far from it (squared
    # Mahalanobis distance of the heading, 1 dof, 99.9%; 0 = off) gets its heading variance
    # widened by the disagreement, so a correction puts its error there (a heading fault)
    # instead of spreading it over the loop
    odometry_check: float = 10.83
    # a drawing whose segment lay between two lines of nearly equal score (its snap a near tie,
    # docs/ALGORITHM.md §I.1) and whose reading contradicts earlier corrections (one of them, or
    # the new one, would yield, §I.8) is read again with that segment on the other line; the
    # first reading that contradicts none is kept, with a note (§I.18)
    near_tie_reading: bool = True
    # consistency guard: a correction after which the map's own measurements (its relative-pose
    # factors) score a chi2 above this quantile of chi2 with 3 x edges dof is tried again with
    # the passes nearest the drawings, then refused with the figures (0 = off)
    consistency_guard: float = 0.999
    # a correction whose passes are joined by chain steps the scans could not check (the
    # odometry check found no match there, so a heading fault can hide in them) is also solved
    # with these kernels on the odometry (a fault then stays where it happened instead of
    # spreading over the stretch), and the more consistent map (§6) of the two is kept
    # (docs/ALGORITHM.md §I.12; "" = off; not tried when `robust` names an odometry kernel)
    unchecked_alternative: str = "odometry=dcs:1"
    # alignment with the scans (docs/ALGORITHM.md §I.11): refused when the aligned poses
    # contradict more than this share of the odometry steps beyond their 99.9% bound
    align_max_contradicted: float = 0.05
    # and when the front end kept fewer loop closures than this between the passes
    align_min_loop_closures: int = 1
    # and when the aligned map is not less inconsistent (§6) than the map before it (False: off)
    align_consistency_guard: bool = True
    # the alignment solves twice, giving each correction's relation dynamic covariance scaling
    # with this Phi (the scans as a second witness: a statement they contradict by more than
    # about 1 cm, sqrt(Phi / K1), yields to them) and with relation_dcs (as firm as elsewhere),
    # and keeps the more consistent map; every later solve while it is in effect uses the Phi
    # it kept (docs/ALGORITHM.md §I.11)
    align_relation_dcs: float = 100.0
    # a candidate solve that holds off more than this share of the statements by more than 5 deg
    # or 0.5 m (alignment.OVERRULED_DEG, OVERRULED_M) is a wrong scan match folding the map, not
    # the scans refining it: it is set aside, and where every candidate is, the alignment is
    # refused (docs/ALGORITHM.md §I.16; 1 = off)
    align_max_overruled: float = 1 / 3
    # §6.1 metric / occupancy export
    grid_resolution: float = 0.05  # [m]
    # §6.2 inconsistency metric: its robustness rules (without them a perfect map scores 100s m^2)
    metric_surface_cells: float = 2.0  # [cells] (a) free space ends this far from the hit surface
    metric_min_stop: float = 0.10  # [m] (a) and at least this far before the hit, along the beam
    metric_grazing_deg: float = 15.0  # [deg] (b) beams meeting a surface below this carve nothing

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if isinstance(value, bool):
                continue
            if isinstance(value, str):
                from hitl_slam.solve import robust_pairs

                robust_pairs(value)
                continue
            if not isinstance(value, int | float) or not math.isfinite(value) or value < 0:
                raise InputError(f"config {f.name} must be a finite number >= 0, got {value!r}")
        for name in (
            "sigma_h",
            "sigma_em",
            "sigma_f",
            "grid_resolution",
            "sigma_t0",
            "sigma_theta0",
        ):
            if getattr(self, name) <= 0:
                raise InputError(f"config {name} must be > 0")
        if self.search_band > 0 and self.drawing_sigma <= 0:
            raise InputError("config drawing_sigma must be > 0 when search_band is > 0")
        if not self.consistency_guard < 1:
            raise InputError(
                "config consistency_guard is a probability: 0 (off) or between 0 and 1, "
                f"e.g. 0.999; got {self.consistency_guard!r}"
            )

        if not self.align_max_contradicted <= 1:
            raise InputError(
                "config align_max_contradicted is a share of the odometry steps, between 0 and "
                f"1, e.g. 0.05; got {self.align_max_contradicted!r}"
            )

        if not self.align_max_overruled <= 1:
            raise InputError(
                "config align_max_overruled is a share of the statements, between 0 and 1, "
                f"e.g. 0.33; got {self.align_max_overruled!r}"
            )

    def replace(self, **changes: Any) -> Config:
        """A copy with some constants changed (validated)."""
        unknown = set(changes) - {f.name for f in dataclasses.fields(self)}
        if unknown:
            raise InputError(f"unknown config key(s): {', '.join(sorted(unknown))}")
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> Config:
        """The configuration ``data`` (:meth:`to_dict`) describes; an unknown key is refused
        (:meth:`replace`). :meth:`known` splits off the keys of a stored configuration that this
        version does not have."""
        return DEFAULT.replace(**data)

    @classmethod
    def known(cls, data: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
        """``data`` split into the keys this version's Config has and the rest (an option a
        session saved before it was deleted: options measured and not kept are deleted, not
        kept off)."""
        names = {f.name for f in dataclasses.fields(cls)}
        return (
            {k: v for k, v in data.items() if k in names},
            {k: v for k, v in data.items() if k not in names},
        )


DEFAULT = Config()
