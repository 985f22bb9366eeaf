"""Reading a torch checkpoint file (``.pth``) as a state_dict, without running pickled code.

``torch.load(weights_only=True)`` refuses anything but tensors and plain containers; what it
refuses, and every other way a file can fail to be a checkpoint (missing, a directory, truncated,
another format, non-tensor entries, NaN weights), is one ConfigError naming the file. Before
torch.load sees the file, its size (from its stat) must be at most :data:`MAX_CHECKPOINT_BYTES`
and it must begin as torch.save writes: a zip archive, or (the legacy format) a pickle of
protocol 2 or later. Used by the exporter's checkpoint loader and by the upstream-weight loaders
of the models.
"""

from __future__ import annotations

import math
import pickletools
import warnings
import zipfile
from pathlib import Path

import torch

from ..data.readers import check_file
from ..errors import ConfigError

# The largest checkpoint radaredge reads: its models' weights are tens of MB (maffnet-vod-full
# about 40 MB); a training run's last.pth, with the optimiser's state, about three times that.
MAX_CHECKPOINT_BYTES = 2 * 2**30
_ZIP_MAGIC = b"PK\x03\x04"  # torch.save since torch 1.6
_PICKLE_MAGIC = tuple(b"\x80" + bytes([p]) for p in (2, 3, 4, 5))  # the legacy format: a pickle, protocol >= 2


def check_checkpoint_file(path: str | Path) -> None:
    """ConfigError naming ``path`` unless it is a regular file of at most
    :data:`MAX_CHECKPOINT_BYTES` that begins as torch.save writes (a zip archive, or a pickle of
    protocol 2 or later): checked from its stat and its first bytes, before torch.load reads it."""
    if not Path(path).exists():
        raise ConfigError(f"checkpoint {path} does not exist")
    check_file(
        path,
        "a torch checkpoint (.pth)",
        MAX_CHECKPOINT_BYTES,
        "radaredge's models' weights are tens of MB, a training run's last.pth a few times that",
        error=ConfigError,
    )
    with open(path, "rb") as f:
        head = f.read(4)
    if not head:
        raise ConfigError(f"checkpoint {path} is empty (0 bytes): not a file written by torch.save")
    if not (head.startswith(_ZIP_MAGIC) or head[:2] in _PICKLE_MAGIC):
        if _pickle_calls_code(path):  # an old-protocol pickle that imports or calls code
            raise ConfigError(
                f"checkpoint {path} is not a readable torch checkpoint: a pickle of objects other than "
                f"tensors and plain containers (radaredge runs no pickled code)"
            )
        raise ConfigError(
            f"checkpoint {path} is not a readable torch checkpoint: it begins with bytes {head!r}, "
            f"not the zip archive (PK\\x03\\x04) or pickle (\\x80 and a protocol >= 2) that "
            f"torch.save writes"
        )


_CODE_OPCODES = {"GLOBAL", "STACK_GLOBAL", "INST", "OBJ", "REDUCE", "NEWOBJ", "NEWOBJ_EX", "BUILD"}


def _pickle_calls_code(path: str | Path) -> bool:
    """Whether a bare (non-zip) pickle file imports or calls anything, read opcode by opcode
    without running it; False for a zip archive or a file that is no pickle at all."""
    if zipfile.is_zipfile(path):
        return False
    try:
        with open(path, "rb") as f:
            return any(op.name in _CODE_OPCODES for op, _, _ in pickletools.genops(f))
    except Exception:  # not a pickle, or a truncated one
        return False


def read_state_dict(path: str | Path) -> dict:
    """The state_dict inside a ``.pth`` (bare, or under OpenPCDet's ``model_state``, ``state_dict`` or
    ``model``), its values tensors; ConfigError naming the file and the problem otherwise."""
    return read_checkpoint(path)[0]


def _load_checkpoint(path: str | Path):
    """The object torch.save wrote to ``path``, loaded without running pickled code; ConfigError
    naming the file and why otherwise."""
    check_checkpoint_file(path)
    try:
        with warnings.catch_warnings():  # torch warns about pickle protocols before refusing
            warnings.simplefilter("ignore")
            obj = torch.load(str(path), map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise ConfigError(f"checkpoint {path} does not exist") from None
    except IsADirectoryError:
        raise ConfigError(f"checkpoint {path} is a directory, not a .pth file") from None
    except Exception as exc:
        if "Unsupported global" in str(exc) or _pickle_calls_code(path):
            why = "a pickle of objects other than tensors and plain containers (radaredge runs no pickled code)"
        elif not zipfile.is_zipfile(path):
            why = "not a file written by torch.save (truncated, or another format)"
        else:
            why = f"damaged ({type(exc).__name__})"
        raise ConfigError(f"checkpoint {path} is not a readable torch checkpoint: {why}") from None
    return obj


def read_checkpoint(path: str | Path) -> tuple[dict, list[str] | None]:
    """(the state_dict of :func:`read_state_dict`, the point feature columns the weights were
    trained with when the file records them: radaredge's training checkpoints carry their card,
    whose ``features`` give the column order the first layer's weights expect; None otherwise)."""
    obj = _load_checkpoint(path)
    features = None
    if isinstance(obj, dict) and isinstance(obj.get("card"), dict) and isinstance(obj["card"].get("features"), list):
        features = [str(f) for f in obj["card"]["features"]]
    for key in ("model_state", "state_dict", "model"):
        if isinstance(obj, dict) and isinstance(obj.get(key), dict):
            obj = obj[key]
    if not isinstance(obj, dict):
        raise ConfigError(f"checkpoint {path}: expected a state_dict mapping, got {type(obj).__name__}")
    bad = [f"{k!r} ({type(v).__name__})" for k, v in obj.items() if not isinstance(k, str) or not torch.is_tensor(v)]
    if bad:
        raise ConfigError(f"checkpoint {path}: state_dict entries must be named tensors; not so: {', '.join(bad[:5])}")
    complex_ = [k for k, v in obj.items() if v.is_complex()]
    if complex_:
        raise ConfigError(f"checkpoint {path}: complex values in {', '.join(complex_[:5])}; network weights are real")
    broken = [k for k, v in obj.items() if v.is_floating_point() and not bool(torch.isfinite(v).all())]
    if broken:
        more = f" and {len(broken) - 5} more" if len(broken) > 5 else ""
        raise ConfigError(
            f"checkpoint {path}: values are not finite (NaN or Inf) in {', '.join(broken[:5])}{more}; "
            f"a diverged training run writes such weights"
        )
    return obj, features


def read_qat_entry(path: str | Path) -> dict | None:
    """The ``qat`` entry of a radaredge training checkpoint made by ``radaredge train --qat``
    (:meth:`radaredge.training.qat.FakeQuantizedLayers.checkpoint_entry`): the int8 settings it
    was fine-tuned for and its learned activation ranges, layer name -> {"input" / "output":
    [min, max]}; None for a checkpoint without one. ConfigError naming the file when the entry is
    malformed."""
    obj = _load_checkpoint(path)
    entry = obj.get("qat") if isinstance(obj, dict) else None
    if entry is None:
        return None
    ranges = entry.get("ranges") if isinstance(entry, dict) else None
    ok = (
        isinstance(ranges, dict)
        and isinstance(entry.get("reduce_range"), bool)
        and isinstance(entry.get("keep_fp32"), list)
        and all(
            isinstance(name, str)
            and isinstance(r, dict)
            and set(r) <= {"input", "output"}
            and all(
                isinstance(v, (list, tuple))
                and len(v) == 2
                and all(isinstance(x, float) and math.isfinite(x) for x in v)
                and v[0] <= v[1]
                for v in r.values()
            )
            for name, r in ranges.items()
        )
    )
    if not ok:
        raise ConfigError(
            f"checkpoint {path}: its 'qat' entry is not what `radaredge train --qat` writes (reduce_range, "
            f"keep_fp32, and ranges: layer -> {{input/output: [min, max]}} with finite min <= max)"
        )
    return entry
