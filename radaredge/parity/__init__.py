"""The parity verb's machinery: typed comparators, one class per output kind
(:mod:`.comparators`), which comparator judges each output of each model (:mod:`.judges`), and
the check itself (:mod:`.check`). The verb is :func:`radaredge.api.parity`."""
