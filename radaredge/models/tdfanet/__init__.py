"""TDFANet (sequential 4D-radar place recognition): the network (:mod:`.model`) and its spec
(:mod:`.spec`), registered as ``tdfanet``."""

from . import spec  # noqa: F401  (registers the spec)
