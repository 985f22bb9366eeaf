"""Quantisation-aware fine-tuning (``radaredge train --qat``): fake quantisation in the training
forward that simulates what ``radaredge export --quantize int8`` writes, so the weights learn
to absorb the int8 rounding before they are quantised.

What is simulated, layer by layer, for every ``nn.Conv1d`` / ``nn.Conv2d`` / ``nn.Linear`` the
export quantises (its Conv / MatMul / Gemm nodes; the card's ``quantization.keep_fp32`` modules
stay fp32 here as there):

- weights: per output channel, symmetric int8 on onnxruntime's grid (the card's
  ``quantization.reduce_range``: [-64, 64] with scale max|w| / 64, else [-127, 127] with
  max|w| / 127). onnxruntime quantises the weights after folding the batch norm that follows a
  layer into them; folding scales each output channel by one factor, and a per-channel
  symmetric grid scales with it, so fake-quantising the unfolded weights is exactly the folded
  weights' quantisation;
- the layer's input: uint8, per tensor, asymmetric, its range the moving average of the
  training batches' min and max (torch.ao's ``FakeQuantize`` with a
  ``MovingAverageMinMaxObserver``, the scale and zero point onnxruntime derives from a range);
- the output of a convolution that ends a ``Sequential`` run Conv [-> BatchNorm] [-> ReLU], or
  that has no batch norm beside it (a detection head's convs): uint8 after the batch norm and
  the ReLU, as the int8 graph quantises the folded conv's output with the ReLU's range.

The ranges are observed while a layer is in training mode and frozen in eval mode (validation
scores the fake-quantised network). They are saved with the weights (``qat`` in best.pth,
:meth:`FakeQuantizedLayers.checkpoint_entry`); the export takes them for those tensors
(:func:`radaredge.exporting.quantize.learned_tensor_ranges`) and calibrates the rest as
before: attention products of two activations, linear layers' outputs (a bias the graph may
add after the quantised MatMul), convolutions whose batch norm a parent's ``forward`` applies.
A layer whose weights its parent uses directly, never calling it (the deformable attention's
offset and weight projections, folded into head-major products), sees no data and is not
simulated; its ranges stay calibrated too.

The network's modules and state dict are untouched (the hooks live beside it), so a QAT
checkpoint loads and exports as any other.
"""

from __future__ import annotations

import contextlib
import fnmatch
from dataclasses import dataclass

import torch
from torch import nn
from torch.ao.quantization import FakeQuantize, MovingAverageMinMaxObserver

from ..cards import ModelCard
from ..errors import ConfigError
from ..exporting.quantize import keep_fp32_patterns, reduce_range

QAT_VERSION = 1
QUANTISED_LAYERS = (nn.Conv1d, nn.Conv2d, nn.Linear)


def weight_grid(seven_bit: bool) -> tuple[int, int]:
    """onnxruntime's symmetric int8 weight range: [-64, 64] with ``reduce_range``, else [-127, 127]."""
    return (-64, 64) if seven_bit else (-127, 127)


def fake_quantize_weight(weight: torch.Tensor, seven_bit: bool) -> torch.Tensor:
    """``weight`` (output channels first) rounded to onnxruntime's per-channel symmetric int8 grid
    (:func:`weight_grid`; scale max|w_c| / qmax per output channel c, zero point 0) and back to
    float, with the straight-through gradient inside the range."""
    qmin, qmax = weight_grid(seven_bit)
    absmax = weight.detach().abs().flatten(1).amax(dim=1)
    scale = torch.where(absmax > 0, absmax / qmax, torch.ones_like(absmax)).float()
    zero = torch.zeros_like(scale, dtype=torch.int32)
    return torch.fake_quantize_per_channel_affine(weight, scale, zero, 0, qmin, qmax)


def activation_fake_quant(device: torch.device) -> FakeQuantize:
    """uint8 per-tensor asymmetric fake quantisation on a moving-average min/max range."""
    return FakeQuantize(
        observer=MovingAverageMinMaxObserver, quant_min=0, quant_max=255, dtype=torch.quint8, reduce_range=False
    ).to(device)


def _chain_end(model: nn.Module, name: str) -> str | None:
    """The module whose output the int8 graph quantises for convolution ``name``: the last of
    Conv [-> BatchNorm] [-> ReLU] in its ``Sequential``, the conv itself when its parent holds no
    batch norm; None when a parent's ``forward`` applies one (the range stays calibrated)."""
    parent_name, _, own = name.rpartition(".")
    parent = model.get_submodule(parent_name) if parent_name else model
    if isinstance(parent, nn.Sequential):
        keys = list(parent._modules)
        end, i = name, keys.index(own) + 1
        for kind in (nn.modules.batchnorm._BatchNorm, nn.ReLU):
            if i < len(keys) and isinstance(parent._modules[keys[i]], kind):
                end = f"{parent_name}.{keys[i]}"
                i += 1
        return end
    if any(isinstance(m, nn.modules.batchnorm._BatchNorm) for m in parent.children()):
        return None
    return name


@dataclass
class _Layer:
    module: nn.Module
    input: FakeQuantize
    output: FakeQuantize | None


class FakeQuantizedLayers:
    """Fake quantisation (module docstring) hooked into ``model``'s quantised layers for ``card``'s
    int8 settings; :meth:`remove` takes it out again. ``model`` must already be on its device."""

    def __init__(self, model: nn.Module, card: ModelCard):
        self.seven_bit = reduce_range(card)
        self.keep_fp32 = keep_fp32_patterns(card)
        device = next(model.parameters()).device
        self.layers: dict[str, _Layer] = {}
        self._handles = []
        self._forced = False
        for name, module in model.named_modules():
            if type(module) not in QUANTISED_LAYERS or self._kept(name):
                continue
            end = _chain_end(model, name) if isinstance(module, (nn.Conv1d, nn.Conv2d)) else None
            layer = _Layer(module, activation_fake_quant(device), activation_fake_quant(device) if end else None)
            self.layers[name] = layer
            module.forward = self._quantised_forward(layer)  # the instance's, over its class's
            if end is not None:
                self._handles.append(model.get_submodule(end).register_forward_hook(self._output_hook(layer)))
        if not self.layers:
            raise ConfigError(f"card {card.name!r}: --qat found no Conv/Linear layer to fake-quantise")

    def _kept(self, name: str) -> bool:
        scopes = [".".join(name.split(".")[:k]) for k in range(1, name.count(".") + 2)]
        return any(fnmatch.fnmatchcase(s, p) for s in scopes for p in self.keep_fp32)

    def _fake_quantize(self, fq: FakeQuantize, x: torch.Tensor, training: bool) -> torch.Tensor:
        """``x`` through ``fq``, its range updated when ``training`` (or :meth:`observing`); ``x``
        as it is while ``fq`` has no range yet (a layer run in eval mode before any training)."""
        observe = training or self._forced
        if not observe and bool(torch.isinf(fq.activation_post_process.min_val)):
            return x
        fq.enable_observer(observe)
        return fq(x)

    @contextlib.contextmanager
    def observing(self):
        """Observe ranges in eval mode too, for the first ranges of a run: an observer that has
        seen no data has none, and the initial validation runs in eval mode."""
        self._forced = True
        try:
            yield
        finally:
            self._forced = False

    def _quantised_forward(self, layer: _Layer):
        """The layer's forward on its fake-quantised input and weights."""
        module, seven_bit = layer.module, self.seven_bit

        def forward(x):
            x = self._fake_quantize(layer.input, x, module.training)
            weight = fake_quantize_weight(module.weight, seven_bit)
            if isinstance(module, nn.Linear):
                return nn.functional.linear(x, weight, module.bias)
            return module._conv_forward(x, weight, module.bias)

        return forward

    def _output_hook(self, layer: _Layer):
        def hook(module, args, output):
            return self._fake_quantize(layer.output, output, module.training)

        return hook

    def remove(self) -> None:
        for h in self._handles:
            h.remove()
        self._handles.clear()
        for layer in self.layers.values():
            layer.module.__dict__.pop("forward", None)

    def state_dict(self) -> dict:
        """The observers' and fake quantisers' buffers by layer (``last.pth``, for ``--resume``)."""
        return {
            name: {"input": layer.input.state_dict(), **({"output": layer.output.state_dict()} if layer.output else {})}
            for name, layer in self.layers.items()
        }

    def load_state_dict(self, state: dict) -> None:
        if sorted(state) != sorted(self.layers):
            raise ConfigError("--resume: the run's fake-quantised layers differ from this card's; use a new --output")
        for name, layer in self.layers.items():
            layer.input.load_state_dict(state[name]["input"])
            if layer.output is not None:
                layer.output.load_state_dict(state[name]["output"])

    def ranges(self) -> dict[str, dict[str, list[float]]]:
        """Layer name -> {"input": [min, max]} and, where simulated, "output": the learned ranges
        (metres, m/s or whatever the tensor holds), those of layers that have seen no data left out."""

        def span(fq: FakeQuantize) -> list[float] | None:
            lo, hi = float(fq.activation_post_process.min_val), float(fq.activation_post_process.max_val)
            return [lo, hi] if lo <= hi else None  # an observer that saw nothing holds +inf / -inf

        out = {}
        for name, layer in self.layers.items():
            entry = {"input": span(layer.input)}
            if layer.output is not None:
                entry["output"] = span(layer.output)
            entry = {k: v for k, v in entry.items() if v is not None}
            if entry:
                out[name] = entry
        return out

    def checkpoint_entry(self) -> dict:
        """What best.pth records under ``qat``: the int8 settings trained for and the ranges."""
        return {
            "version": QAT_VERSION,
            "reduce_range": self.seven_bit,
            "keep_fp32": list(self.keep_fp32),
            "ranges": self.ranges(),
        }


def resume_signature(recipe: dict) -> dict:
    """A recipe's options (``dataclasses.asdict``) as a resume signature holds them: without the
    ``qat`` options when ``qat`` is off, so that a run written before they existed resumes."""
    return recipe if recipe.get("qat") else {k: v for k, v in recipe.items() if not k.startswith("qat")}


def start_qat(model: nn.Module, card: ModelCard, precision: str, fine_tunes: bool) -> FakeQuantizedLayers:
    """:class:`FakeQuantizedLayers` on ``model`` for a ``--qat`` run: ConfigError unless the run
    fine-tunes trained weights (``--checkpoint`` or ``--resume``) in fp32."""
    if not fine_tunes:
        raise ConfigError(
            "--qat fine-tunes trained weights: pass --checkpoint best.pth (or --resume a --qat run); "
            "train in fp32 first"
        )
    if precision != "fp32":
        raise ConfigError(f"--qat simulates the int8 graph on fp32 training; drop precision={precision}")
    return FakeQuantizedLayers(model, card)
