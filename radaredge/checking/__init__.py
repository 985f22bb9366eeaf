"""The parity verb's machinery: the check itself (:mod:`.check`), on synthetic cases or on a
recording (:mod:`.recording`), with the capacity tally (:mod:`.capacity`). Each output is judged
by the comparator its graph's spec names (:mod:`radaredge.models.comparators`). The verb is
:func:`radaredge.api.parity`."""
