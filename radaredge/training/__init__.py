"""Training: the paper's losses and recipes, behind the ``radaredge train`` verb.

- :mod:`.losses`: TDFANet's lazy quadruplet loss (eq. 10).
- :mod:`.places`: drives of a place-recognition recording as training windows, the split by
  drive, and the tuple mining (positives within 5 m, negatives beyond 10 m).
- :mod:`.tdfanet`: the TDFANet recipe (Adam 8e-4, exponential decay 0.9 per epoch, validation
  Recall@1/5/10 per epoch, best checkpoint, resume).
"""
