"""Reading a torch checkpoint file (``.pth``) as a state_dict, without running pickled code.

``torch.load(weights_only=True)`` refuses anything but tensors and plain containers; what it
refuses, and every other way a file can fail to be a checkpoint (missing, a directory, truncated,
another format, non-tensor entries, NaN weights), is one ConfigError naming the file. Used by
the exporter's checkpoint loader and by the upstream-weight loaders of the models.
"""

from __future__ import annotations

import pickletools
import warnings
import zipfile
from pathlib import Path

import torch

from ..errors import ConfigError


_CODE_OPCODES = {"GLOBAL", "STACK_GLOBAL", "INST", "OBJ", "REDUCE", "NEWOBJ", "NEWOBJ_EX", "BUILD"}


def _pickle_calls_code(path: str | Path) -> bool:
    """Whether a bare (non-zip) pickle file imports or calls anything, read opcode by opcode
    without running it; False for a zip archive or a file that is no pickle at all."""
    if zipfile.is_zipfile(path):
        return False
    try:
        with open(path, "rb") as f:
            return any(op.name in _CODE_OPCODES for op, _, _ in pickletools.genops(f))
    except Exception:                        # not a pickle, or a truncated one
        return False


def read_state_dict(path: str | Path) -> dict:
    """The state_dict inside a ``.pth`` (bare, or under OpenPCDet's ``model_state``, ``state_dict`` or
    ``model``), its values tensors; ConfigError naming the file and the problem otherwise."""
    return read_checkpoint(path)[0]


def read_checkpoint(path: str | Path) -> tuple[dict, list[str] | None]:
    """(the state_dict of :func:`read_state_dict`, the point feature columns the weights were
    trained with when the file records them: radaredge's training checkpoints carry their card,
    whose ``features`` give the column order the first layer's weights expect; None otherwise)."""
    try:
        with warnings.catch_warnings():            # torch warns about pickle protocols before refusing
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
        raise ConfigError(f"checkpoint {path}: values are not finite (NaN or Inf) in {', '.join(broken[:5])}{more}; "
                          f"a diverged training run writes such weights")
    return obj, features
