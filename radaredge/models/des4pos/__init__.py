"""Des4Pos (text-to-point-cloud localisation): the network (:mod:`.model`) with its MiniLM text
backbone (:mod:`.minilm`), Text2Pos-format weights (:mod:`.weights`), the spec of its three
graphs (:mod:`.spec`) and its bench tasks (:mod:`.bench`), registered as ``des4pos``."""

from ...registry import ModelFamily, register_family

register_family(ModelFamily("des4pos", sections=("cell", "submap", "text", "fine"), spec=f"{__name__}.spec:spec_for"))
