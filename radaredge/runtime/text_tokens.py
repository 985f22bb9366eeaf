"""Description -> hint sentences -> token ids, offline (numpy + ``tokenizers`` only, no torch).

The Des4Pos text encoder graph takes ``input_ids`` [H, L] int64 and ``attention_mask`` [H, L]
int64: one row per hint sentence, padded to the longest hint (pad id 0, mask 0), at most
``max_tokens`` tokens each ([CLS] and [SEP] included). Tokenisation is the backbone's own
``tokenizer.json`` (WordPiece for MiniLM) read by the ``tokenizers`` library; the exporter copies
that file into the bundle, so an embedded app needs nothing from a model hub.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import ConfigError, InputError

_SENTENCE_END = re.compile(r"(?<=[.!?])\s+")


def split_hints(text: str) -> list[str]:
    """Split a description into hint sentences at '.', '!' or '?' followed by white space."""
    if not isinstance(text, str):
        raise InputError(f"a description must be text, got {type(text).__name__}")
    return [s.strip() for s in _SENTENCE_END.split(text.strip()) if s.strip()]


def load_tokenizer(path: str | Path):
    """A ``tokenizers.Tokenizer`` from ``tokenizer.json`` (file or the directory holding it)."""
    # optional: tokenizers (eval and export extras) is needed by Des4Pos only
    from tokenizers import Tokenizer

    path = Path(path)
    if path.is_dir():
        path = path / "tokenizer.json"
    if not path.is_file():
        raise ConfigError(f"no tokenizer at {path}; a Des4Pos bundle carries tokenizer.json beside its graphs")
    try:
        tok = Tokenizer.from_file(str(path))
    except Exception as exc:  # tokenizers raises its own Exception type with serde's message
        raise InputError(f"{path}: not a readable tokenizer.json ({' '.join(str(exc).split())[:160]})") from None
    tok.no_padding()
    tok.no_truncation()
    return tok


def encode_hints(tokenizer, hints: list[str], max_tokens: int, max_hints: int) -> tuple[np.ndarray, np.ndarray]:
    """Token ids and attention mask [H, L] (L = longest hint) for ``hints``.

    InputError when there is no hint, more than ``max_hints``, or a hint longer than
    ``max_tokens`` tokens (named by number and text, with its token count).
    """
    if not hints:
        raise InputError('the description has no hint sentence; e.g. "The pose is north of a red box."')
    if len(hints) > max_hints:
        raise InputError(f"the description has {len(hints)} hint sentences; this model takes at most {max_hints}")
    rows = []
    for i, h in enumerate(hints):
        ids = tokenizer.encode(h).ids
        if len(ids) > max_tokens:
            raise InputError(
                f"hint {i + 1} ({h!r}) is {len(ids)} tokens long; this model takes at most {max_tokens} "
                f"per hint sentence: split it into shorter sentences"
            )
        rows.append(ids)
    length = max(len(r) for r in rows)
    ids = np.zeros((len(rows), length), np.int64)
    mask = np.zeros((len(rows), length), np.int64)
    for i, r in enumerate(rows):
        ids[i, : len(r)] = r
        mask[i, : len(r)] = 1
    return ids, mask
