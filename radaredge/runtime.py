"""Torch-free runtime: load an exported ``.onnx`` and run it on raw radar frames.

Imports only numpy, onnxruntime and radaredge's own torch-free modules (cards, errors, ort), so
an embedded application needs neither torch nor the radaredge model code::

    from radaredge import runtime
    model = runtime.load("export/tdfanet.onnx")
    out = model.run([scan_t2, scan_t1, scan_t0])     # oldest first, each [N_k, 5] x,y,z,v_r,rcs
    out["descriptor_normalized"]                      # 256-d place descriptor
"""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Sequence

import numpy as np
import onnxruntime as ort

from .cards import ModelCard, card_from_yaml
from .errors import CapacityError, InputError
from .ort import make_session, run_session

META_PREFIX = "radaredge."


class RadarModel:
    """An exported radaredge pipeline: ``.card`` (from the ONNX metadata) and ``.run(frames)``."""

    def __init__(self, session: ort.InferenceSession, path: Path):
        self.session = session
        self.path = path
        meta = session.get_modelmeta().custom_metadata_map
        if META_PREFIX + "card" not in meta:
            raise InputError(f"{path} is not a radaredge export: its metadata has no {META_PREFIX}card entry")
        self.metadata = meta
        self.card: ModelCard = card_from_yaml(meta[META_PREFIX + "card"])
        self.features: list[str] = json.loads(meta[META_PREFIX + "features"])
        self.input_names = [i.name for i in session.get_inputs()]
        self.output_names = [o.name for o in session.get_outputs()]
        self.weights_sha256: str | None = meta.get(META_PREFIX + "weights_sha256")
        self.frames = int(self.card.get("frames", 1))
        self.frame_rate = float(self.card.get("frame_rate", 10.0))

    def validate(self, frames: Sequence[np.ndarray]) -> list[np.ndarray]:
        """Check frame count, shapes, dtype and finiteness against the card; return float32 copies."""
        if isinstance(frames, np.ndarray):
            frames = [frames] if self.frames == 1 else list(frames)
        if len(frames) != self.frames:
            raise InputError(f"{self.card.name} takes {self.frames} frame(s) (oldest first), got {len(frames)}")
        cols = len(self.features)
        out = []
        for k, f in enumerate(frames):
            a = np.asarray(f)
            if a.dtype.kind not in "fiu":
                raise InputError(f"frame {k}: expected a numeric array of points, got dtype {a.dtype}")
            if a.ndim != 2 or a.shape[1] != cols:
                raise InputError(f"frame {k}: expected shape [N, {cols}] with columns {self.features}, got {a.shape}")
            a = np.ascontiguousarray(a, np.float32)
            bad = ~np.isfinite(a)
            if bad.any():
                row, col = np.argwhere(bad)[0]
                raise InputError(f"frame {k}: non-finite value {a[row, col]} at point {row}, column "
                                 f"'{self.features[col]}' ({int(bad.any(1).sum())} point(s) affected)")
            out.append(a)
        return out

    def feeds(self, frames: Sequence[np.ndarray], timestamps: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """The graph's input feeds for one window: the validated frames (:meth:`validate`) and,
        when the graph takes them, ``timestamps`` float32 [K] (s, oldest first, strictly
        increasing; default: the card's frame rate)."""
        frames = self.validate(frames)
        feeds = {f"points_{k}": f for k, f in enumerate(frames)} if self.frames > 1 else {self.input_names[0]: frames[0]}
        if "timestamps" in self.input_names:
            if timestamps is None:
                ts = np.arange(self.frames, dtype=np.float32) / self.frame_rate
            else:
                ts = np.asarray(timestamps, np.float32)
                if ts.shape != (self.frames,) or not np.isfinite(ts).all():
                    raise InputError(f"timestamps: expected {self.frames} finite values in seconds, got {timestamps!r}")
                if (np.diff(ts) <= 0).any():
                    raise InputError(f"timestamps must increase strictly (oldest frame first), got {ts.tolist()}")
            feeds["timestamps"] = ts
        return feeds

    def run(self, frames: Sequence[np.ndarray], timestamps: Sequence[float] | None = None) -> dict[str, np.ndarray]:
        """Run the pipeline. ``timestamps`` (s, oldest first) default to the card's frame rate."""
        out = run_session(self.session, self.feeds(frames, timestamps))
        if "spa_overflow" in out and bool(out["spa_overflow"]):
            raise CapacityError(f"the scan has {int(out['num_pillars'])} non-empty pillars but {self.card.name}'s "
                                f"sparse pillar attention holds spa.capacity = {self.card.get('spa.capacity')}; "
                                "export with a larger spa.capacity (--config) or crop the scan")
        if "cfa_converged" in out and not bool(out["cfa_converged"]):
            self._cfa_not_converged()
        return out

    def _cfa_not_converged(self) -> None:
        """MAFF-Net's clustering map is not the one its method defines: the card's ``cfa.not_converged``
        says whether that is an error (default for DBSCAN: more scan points than its capacity) or a
        warning (default for GridDensityBEV: components longer than its max-pool steps)."""
        cfa = self.card.get("cfa", {}) or {}
        method = cfa.get("method", "grid_density")
        policy = cfa.get("not_converged") or ("error" if method == "dbscan" else "warn")
        if method == "dbscan":
            msg = (f"the scan has more points inside the range than {self.card.name}'s DBSCAN clusters "
                   f"(cfa.dbscan.capacity = {self.card.get('cfa.dbscan.capacity')}); the points beyond it were "
                   "left out of the clustering map; export with a larger capacity (--config) or crop the scan")
        else:
            msg = (f"{self.card.name}'s GridDensityBEV components did not converge in cfa.grid.cc_iterations = "
                   f"{self.card.get('cfa.grid.cc_iterations')} max-pool steps (the fork's partial labels); "
                   "cc_mode: exact gives true components")
        if policy == "error":
            raise CapacityError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)


def load(path: str | Path, threads: int = 2) -> RadarModel:
    """Load an exported radaredge ``.onnx`` for inference on ``threads`` CPU threads."""
    path = Path(path)
    return RadarModel(make_session(path, threads=threads), path)
