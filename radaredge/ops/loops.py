"""A data-dependent loop that exports as one ONNX ``Loop`` and runs as a plain loop in eager torch.

``fixed_point_loop(cond, body, state)`` iterates ``state = body(*state)`` while
``cond(*state)`` holds. While torch.export traces (radaredge's ONNX export), it is a
``torch.while_loop``, which becomes an ONNX ``Loop`` node. In eager torch it is a plain Python
loop with the same rounds: an eager ``while_loop`` would go through torch.compile and recompile
whenever a loop-carried shape changes from call to call, e.g. the NMS candidate count.
"""

from __future__ import annotations

from typing import Callable

import torch
from torch._higher_order_ops.while_loop import while_loop


def fixed_point_loop(cond: Callable, body: Callable, state: tuple) -> tuple:
    """The final loop-carried tensors; ``cond`` returns a 0-d bool tensor, ``body`` a tuple of
    tensors shaped like ``state``."""
    if torch.compiler.is_exporting():
        return tuple(while_loop(cond, body, state))
    while bool(cond(*state)):
        state = tuple(body(*state))
    return state
