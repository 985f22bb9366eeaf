"""How full do VoD 5-frame clouds make MAFF-Net's fixed-size stages? (sizes spa.capacity and
cfa.dbscan.capacity in the VoD cards).

For 12 synthetic VoD ``radar_5frames``-style clouds (5 consecutive scans moved into the newest
scan's frame; even seeds with dense traffic, odd seeds with the default scene), with and without
the camera field-of-view crop, counts:
- ``points``: rows of the cloud;
- ``scan_points``: rows upstream's data processor keeps (x and y inside the point-cloud range),
  the points DBSCAN clusters;
- ``pillars``: non-empty pillars of the VoD grid, the slots the sparse pillar attention needs.

Writes benchmarks/results/maffnet-capacity-<date>.json and prints the maxima against the card's
capacities. Run: ``python benchmarks/maffnet_capacity.py``.
"""

from __future__ import annotations

import sys

import numpy as np
import torch
from result_file import save_result

from radaredge.cards import load_card
from radaredge.data.synthetic import generate_sequence, vod_accumulated_table
from radaredge.models import create_model
from radaredge.models.maffnet.rcnn import scan_points
from radaredge.models.maffnet.spec import DENSE_TRAFFIC, VOD_CAMERA_FOV_DEG

SEEDS = range(12)


def measure(card_name: str = "maffnet-vod-full-dbscan") -> dict:
    card = load_card(card_name)
    model = create_model(card)
    r = card.get("pillars.point_cloud_range")
    rows = []
    for seed in SEEDS:
        dense = seed % 2 == 0
        seq = generate_sequence(5, seed=seed, **(DENSE_TRAFFIC if dense else {}))
        for crop in (VOD_CAMERA_FOV_DEG, None):
            pts = torch.from_numpy(vod_accumulated_table(seq, crop))
            with torch.no_grad():
                _, pillars, _ = model.pillar_stage(pts, reference=False)
            rows.append(
                {
                    "seed": seed,
                    "dense_traffic": dense,
                    "fov_crop_deg": crop,
                    "points": len(pts),
                    "scan_points": int(scan_points(pts, r)[2].sum()),
                    "pillars": int(pillars),
                }
            )
    out = {
        "card": card_name,
        "spa_capacity": card.get("spa.capacity"),
        "dbscan_capacity": card.get("cfa.dbscan.capacity"),
        "clouds": rows,
    }
    for crop in (VOD_CAMERA_FOV_DEG, None):
        sub = [x for x in rows if x["fov_crop_deg"] == crop]
        key = "camera_fov" if crop else "no_crop"
        out[key] = {k: int(np.max([x[k] for x in sub])) for k in ("points", "scan_points", "pillars")}
    return out


def main() -> int:
    result = measure()
    save_result("maffnet-capacity", result)
    for key in ("camera_fov", "no_crop"):
        m = result[key]
        print(
            f"{key}: at most {m['pillars']} pillars (spa.capacity {result['spa_capacity']}, "
            f"{result['spa_capacity'] / m['pillars']:.1f}x), {m['scan_points']} scan points "
            f"(cfa.dbscan.capacity {result['dbscan_capacity']}, "
            f"{result['dbscan_capacity'] / m['scan_points']:.1f}x), "
            f"{m['points']} points"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
