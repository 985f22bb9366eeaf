"""TDFANet (sequential 4D-radar place recognition): the network (:mod:`.model`) and its spec
(:mod:`.spec`), registered as ``tdfanet``."""

from ...registry import ModelFamily, register_family

register_family(ModelFamily("tdfanet", sections=("preprocess", "pillars", "network"), spec=f"{__name__}.spec:spec_for"))
