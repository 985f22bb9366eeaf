"""What the graph's fixed capacities did over a recording (``parity-check --data``).

A graph masks what it cannot use instead of failing, and says so in its outputs: ``input_flags``
per frame (:mod:`radaredge.runtime.flags`: points outside the range, a full pillar or another
capacity, components that stopped short, implausible values), MAFF-Net's ``num_pillars`` and
``spa_overflow`` (non-empty pillars against the sparse pillar attention's ``spa.capacity``;
the runtime refuses an overflowing scan) and ``cfa_converged`` (DBSCAN: False when scan points
beyond ``cfa.dbscan.capacity`` were left out of the clustering; GridDensityBEV: False when its
max-pool components stopped at ``cfa.grid.cc_iterations``), TDFANet's ``ego_valid``.
:class:`CapacityTally` summarises the graph's own outputs over the recording and, beside them,
counts on each scan as fed how many points each rule drops: outside ``point_cloud_range`` (the
voxel outside the grid, as the graph decides it), beyond ``max_points_per_pillar`` in their
pillar (input order; of the scan as given, so for TDFANet, whose dynamic-point removal comes
first, an upper bound), implausible values (the card's ``plausible``), and for a DBSCAN map the
scan points it clusters (x and y inside the range) against its capacity.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..cards import ModelCard
from ..models.maffnet.model import SpaConfig
from ..ops.dbscan import DbscanConfig
from ..ops.grid_density import GridDensityConfig
from ..ops.input_flags import column_bounds
from ..ops.pillars import PillarConfig
from ..runtime.flags import BITS

FLAG_NAMES = {bit: text.split(":")[0] for bit, text in BITS.items()}


def point_counts(points: np.ndarray, card: ModelCard, pillars: PillarConfig) -> dict[str, int]:
    """Per scan ``points`` [N, F] (the card's columns): points, implausible, outside the grid,
    beyond ``max_points_per_pillar`` in their pillar (input order) and, for a DBSCAN map, the
    scan points it clusters (finite, x and y within the range, bounds included)."""
    pts = np.asarray(points, np.float32)
    lo, hi = column_bounds(card)
    implausible = ((pts < np.asarray(lo, np.float32)) | (pts > np.asarray(hi, np.float32))).any(1)
    usable = np.isfinite(pts).all(1) & ~implausible
    xyz = pts[:, [card.features.index(c) for c in ("x", "y", "z")]]
    xyz = np.where(usable[:, None], xyz, np.float32(0))
    r = np.asarray(pillars.point_cloud_range, np.float32)
    size = np.asarray(pillars.voxel_size, np.float32)
    coords = np.floor((xyz - r[:3]) / size).astype(np.int64)  # float32 arithmetic, as the graph
    grid = np.asarray(pillars.grid_size, np.int64)
    inside = usable & ((coords >= 0) & (coords < grid)).all(1)
    key = coords[inside, 0] * int(grid[1]) + coords[inside, 1]
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    first = np.searchsorted(sorted_key, sorted_key, side="left")
    rank = np.arange(len(sorted_key)) - first  # points before it in its pillar
    x, y = xyz[:, 0], xyz[:, 1]
    scan = usable & (x >= r[0]) & (x <= r[3]) & (y >= r[1]) & (y <= r[4])
    return {
        "points": int(len(pts)),
        "implausible": int(implausible.sum()),
        "out_of_range": int((usable & ~inside).sum()),
        "over_pillar_cap": int((rank >= pillars.max_points_per_pillar).sum()),
        "scan_points": int(scan.sum()),
    }


@dataclass
class CapacityTally:
    """The capacity outputs of a graph over the cases of a recording (module docstring)."""

    card: ModelCard
    frame_inputs: list[str]
    rows: list[dict] = field(default_factory=list)

    def __post_init__(self):
        self.pillars = self.card.section("pillars", PillarConfig)
        self.cfa_method = self.card.get("cfa.method", "grid_density")

    def add(self, name: str, feeds: dict, got: dict) -> None:
        """One case: its feeds and the graph's outputs."""
        flags = np.asarray(got.get("input_flags", np.zeros(len(self.frame_inputs), np.int32))).reshape(-1)
        frames = []
        for k, inp in enumerate(self.frame_inputs):
            row = point_counts(feeds[inp], self.card, self.pillars)
            row["flags"] = int(flags[k]) if k < len(flags) else 0
            frames.append(row)
        case = {"case": name, "frames": frames}
        for out in ("num_pillars", "spa_overflow", "cfa_converged"):
            if out in got:
                case[out] = np.asarray(got[out]).item()
                case[out] = bool(case[out]) if out != "num_pillars" else int(case[out])
        if "ego_valid" in got:
            case["ego_valid"] = [bool(v) for v in np.asarray(got["ego_valid"]).reshape(-1)]
        self.rows.append(case)

    def summary(self) -> dict:
        frames = [f for r in self.rows for f in r["frames"]]
        n = len(frames)
        out = {
            "cases": len(self.rows),
            "frames": n,
            "points": sum(f["points"] for f in frames),
            "points_out_of_range": sum(f["out_of_range"] for f in frames),
            "points_over_pillar_cap": sum(f["over_pillar_cap"] for f in frames),
            "points_implausible": sum(f["implausible"] for f in frames),
            "max_points_per_pillar": self.pillars.max_points_per_pillar,
            "input_flags": {name: sum(bool(f["flags"] & bit) for f in frames) for bit, name in FLAG_NAMES.items()},
        }
        if "num_pillars" in (self.rows[0] if self.rows else {}):
            pillars = [r["num_pillars"] for r in self.rows]
            spa = self.card.section("spa", SpaConfig)
            out["spa"] = {
                "capacity": spa.capacity,
                "enabled": spa.enabled,
                "max_pillars": max(pillars),
                "mean_pillars": float(np.mean(pillars)),
                "overflow_cases": [r["case"] for r in self.rows if r.get("spa_overflow")],
            }
        if "cfa_converged" in (self.rows[0] if self.rows else {}):
            not_converged = [r["case"] for r in self.rows if not r["cfa_converged"]]
            if self.cfa_method == "dbscan":
                scan = [r["frames"][0]["scan_points"] for r in self.rows]
                cap = self.card.section("cfa.dbscan", DbscanConfig).capacity
                out["cfa"] = {
                    "method": "dbscan",
                    "capacity": cap,
                    "max_scan_points": max(scan),
                    "mean_scan_points": float(np.mean(scan)),
                    "over_capacity_cases": [r["case"] for r, s in zip(self.rows, scan) if s > cap],
                    "not_converged_cases": not_converged,
                }
            else:
                grid = self.card.section("cfa.grid", GridDensityConfig)
                out["cfa"] = {
                    "method": "grid_density",
                    "cc_mode": grid.cc_mode,
                    "cc_iterations": grid.cc_iterations,
                    "not_converged_cases": not_converged,
                }
        if self.rows and "ego_valid" in self.rows[0]:
            valid = [v for r in self.rows for v in r["ego_valid"]]
            out["ego_valid"] = {"valid": int(sum(valid)), "frames": len(valid)}
        return out

    def to_dict(self) -> dict:
        return {"summary": self.summary(), "cases": self.rows}

    def lines(self, unit: str = "frame") -> list[str]:
        if not self.rows:
            return []
        s = self.summary()
        n, cases = s["frames"], s["cases"]

        def share(a: int, b: int) -> str:
            return f"{a:,} ({100 * a / b:.1f} %)" if b else f"{a:,}"

        fed = f"{cases} {unit}s" + (f", {n} scans fed" if n != cases else "")
        out = [
            f"capacity over the recording ({fed}; graph outputs, and point counts on the scans as fed):",
            f"  points {s['points']:,}: outside point_cloud_range {share(s['points_out_of_range'], s['points'])}, "
            f"beyond max_points_per_pillar {s['max_points_per_pillar']} "
            f"{share(s['points_over_pillar_cap'], s['points'])}"
            + (f", implausible {share(s['points_implausible'], s['points'])}" if s["points_implausible"] else ""),
            "  input_flags, scans with the bit: " + ", ".join(f"{k} {v}/{n}" for k, v in s["input_flags"].items()),
        ]
        spa = s.get("spa")
        if spa and spa["enabled"]:
            out.append(
                f"  spa: non-empty pillars max {spa['max_pillars']:,} (mean {spa['mean_pillars']:.0f}) of "
                f"spa.capacity {spa['capacity']:,} ({100 * spa['max_pillars'] / spa['capacity']:.0f} % "
                f"at most); "
                f"spa_overflow in {len(spa['overflow_cases'])} of {cases}"
                + (f": {', '.join(spa['overflow_cases'][:6])}" if spa["overflow_cases"] else "")
            )
        cfa = s.get("cfa")
        if cfa and cfa["method"] == "dbscan":
            out.append(
                f"  cfa dbscan: scan points max {cfa['max_scan_points']:,} (mean {cfa['mean_scan_points']:.0f}) "
                f"of cfa.dbscan.capacity {cfa['capacity']:,} "
                f"({100 * cfa['max_scan_points'] / cfa['capacity']:.0f} % at most); cfa_converged false "
                f"(points beyond capacity left out) in "
                f"{len(cfa['not_converged_cases'])} of {cases}"
                + (f": {', '.join(cfa['not_converged_cases'][:6])}" if cfa["not_converged_cases"] else "")
            )
        elif cfa:
            out.append(
                f"  cfa grid_density ({cfa['cc_mode']}, cc_iterations {cfa['cc_iterations']}): cfa_converged "
                f"false in {len(cfa['not_converged_cases'])} of {cases}"
                + (f": {', '.join(cfa['not_converged_cases'][:6])}" if cfa["not_converged_cases"] else "")
            )
        ego = s.get("ego_valid")
        if ego:
            out.append(f"  ego velocity: ego_valid in {ego['valid']} of {ego['frames']} scans")
        return out
