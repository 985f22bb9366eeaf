"""Des4Pos (text-to-point-cloud localisation): the network (:mod:`.model`) with its MiniLM text
backbone (:mod:`.minilm`), Text2Pos-format weights (:mod:`.weights`) and the spec of its three
graphs (:mod:`.spec`), registered as ``des4pos``."""

from . import spec  # noqa: F401  (registers the spec)
