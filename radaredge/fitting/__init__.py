"""Weights fitted to synthetic data, as test articles for int8 (not trained models).

Seeded weights give scores without structure, so an int8 parity check on them measures
tie-breaking. Each module here fits a card's layers to a synthetic task until its outputs
separate, writes a checkpoint that ``radaredge export --checkpoint`` loads, and runs as
``python -m radaredge.fitting.<module> --out <checkpoint.pth>`` (TDFANet is trained for real
by ``radaredge train``, :mod:`radaredge.training`):

- :mod:`radaredge.fitting.maffnet_head`: MAFF-Net's anchor head (and, optionally, its BEV
  backbone), fitted with OpenPCDet's target assignment and losses on synthetic VoD scans.

They need torch (the export extra); importing this package imports neither.
"""
