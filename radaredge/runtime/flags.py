"""The bits of a point-cloud graph's ``input_flags`` output: what the graph did with its input,
per frame (torch-free; the graph computes them in :mod:`radaredge.ops.input_flags`).

The graph masks what it cannot use instead of failing (a NaN point, a point outside the range),
so a caller that feeds it directly (a C or C++ app) learns from this output what happened
without re-implementing radaredge.runtime's checks. Each graph with the output documents the
bits in its metadata (``radaredge.input_flags``):

=====  ===================  ===============================================================
bit    name                 set for a frame when
=====  ===================  ===============================================================
1      ``non_finite``       a point had a NaN or Inf value in some column; it was left out
2      ``time_order``       its timestamp is not finite, or not after the previous frame's
4      ``out_of_range``     a finite point lay outside the card's point_cloud_range; dropped
8      ``capacity``         a fixed capacity overflowed: a pillar already held
                            ``max_points_per_pillar`` points (later ones dropped), or a
                            model-specific capacity (MAFF-Net's sparse pillar attention or
                            DBSCAN points)
16     ``not_converged``    connected components stopped before converging (MAFF-Net's
                            GridDensityBEV max-pool components)
32     ``implausible``      a point had a value outside its column's plausible range (the
                            card's ``plausible``, e.g. |v_r| > 100 m/s); it was left out
=====  ===================  ===============================================================

radaredge.runtime refuses non-finite points and unordered timestamps before the graph runs, so
those two bits reach its callers only as an error; so does ``implausible`` for a card whose
``implausible`` policy is ``refuse``. The other bits are information. A graph lists the bits
that mean wrong input in its metadata (``radaredge.input_errors``).
"""

from __future__ import annotations

from ..cards import implausible_policy

NON_FINITE, TIME_ORDER, OUT_OF_RANGE, CAPACITY, NOT_CONVERGED, IMPLAUSIBLE = 1, 2, 4, 8, 16, 32
BITS = {
    NON_FINITE: "non_finite: a point had a NaN or Inf value; it was left out",
    TIME_ORDER: "time_order: the frame's timestamp is not finite, or not after the previous frame's",
    OUT_OF_RANGE: "out_of_range: points outside the card's point_cloud_range were dropped",
    CAPACITY: "capacity: a fixed capacity overflowed (points beyond max_points_per_pillar in a pillar, or a "
    "model's pillar or clustering capacity); what did not fit was left out",
    NOT_CONVERGED: "not_converged: connected components stopped before converging",
    IMPLAUSIBLE: "implausible: points with a value outside its column's plausible range were left out",
}
OUTPUT = "input_flags"
INPUT_ERRORS = NON_FINITE | TIME_ORDER  # bits that always mean the input was wrong, not just informative


def input_error_bits(card) -> int:
    """The ``input_flags`` bits that mean a frame of ``card`` was wrong: non-finite values and
    unordered timestamps always, implausible values when the card's ``implausible`` is ``refuse``."""
    return INPUT_ERRORS | (IMPLAUSIBLE if implausible_policy(card) == "refuse" else 0)


def describe(flags: int) -> list[str]:
    """The descriptions of the bits set in ``flags``."""
    return [text for bit, text in BITS.items() if int(flags) & bit]
