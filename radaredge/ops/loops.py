"""A data-dependent loop that exports as one ONNX ``Loop`` and runs as a plain loop in eager torch.

``fixed_point_loop(cond, body, state)`` iterates ``state = body(*state)`` while
``cond(*state)`` holds. While torch.export traces (radaredge's ONNX export), it is a
``torch.while_loop``, which becomes an ONNX ``Loop`` node. In eager torch it is a plain Python
loop with the same rounds: an eager ``while_loop`` would go through torch.compile and recompile
whenever a loop-carried shape changes from call to call, e.g. the NMS candidate count.
A loop with a known bound whose body changes nothing once ``cond`` fails can skip the
condition off the CPU (``max_rounds``): on CUDA each test of ``cond`` is a device-to-host sync,
and on the meta device it cannot be evaluated at all.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch._higher_order_ops.while_loop import while_loop


def fixed_point_loop(cond: Callable, body: Callable, state: tuple, max_rounds: int | None = None) -> tuple:
    """The final loop-carried tensors; ``cond`` returns a 0-d bool tensor, ``body`` a tuple of
    tensors shaped like ``state``. ``max_rounds``: ``cond`` is false after at most this many
    rounds and ``body`` leaves the result unchanged once it is, so eager torch off the CPU runs
    exactly ``max_rounds`` rounds without reading ``cond`` (same result, no host sync)."""
    if torch.compiler.is_exporting():
        return tuple(while_loop(cond, body, state))
    if max_rounds is not None and state[0].device.type != "cpu":
        for _ in range(max_rounds):
            state = tuple(body(*state))
        return state
    while bool(cond(*state)):
        state = tuple(body(*state))
    return state
