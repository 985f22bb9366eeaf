"""The evaluations ``eval`` runs, by the name a model's spec gives in ``evaluation``, and what
``eval`` was given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..cards import ModelCard
from ..errors import ConfigError
from .detection import evaluate_detection, int8_ap_loss
from .localisation import evaluate_localization as localize
from .places import evaluate


@dataclass(frozen=True)
class EvalInputs:
    """What ``eval`` was given; each model's task (:data:`EVALUATIONS`) takes what it needs and
    refuses the rest. Place recognition: ``database``/``queries`` drives, ``radius`` (m),
    ``checkpoint`` and ``reference``; localisation: a cell ``map``; detection: a labelled set
    ``data`` with its ``split`` and ``dataset`` layout."""

    database: str | None = None
    queries: str | None = None
    map: str | None = None
    data: str | None = None
    split: str = "val"
    dataset: str | None = None
    checkpoint: str | None = None
    radius: float = 5.0
    reference: bool = True
    progress: Callable | None = None

    def require(self, task: str, needed: tuple[str, ...], card_name: str, uses: tuple[str, ...] = ()) -> None:
        """ConfigError unless exactly the inputs ``needed`` (of database, queries, map, data) are
        given and no option outside ``uses`` (of checkpoint, radius, reference, split, dataset) was set."""
        missing = [n for n in needed if getattr(self, n) is None]
        extra = [n for n in ("database", "queries", "map", "data") if n not in needed and getattr(self, n) is not None]
        options = (
            ("checkpoint", "checkpoint", self.checkpoint is not None),
            ("radius", "radius", self.radius != 5.0),
            ("reference", "no-reference", not self.reference),
            ("split", "split", self.split != "val"),
            ("dataset", "dataset", self.dataset is not None),
        )  # (name, option, set)
        extra += [option for name, option, given in options if given and name not in uses]
        if missing or extra:
            raise ConfigError(
                f"{card_name} is evaluated by {task} on {', '.join('--' + n for n in needed)}"
                + (f"; missing {', '.join('--' + n for n in missing)}" if missing else "")
                + (f"; {', '.join('--' + n for n in extra)} not used" if extra else "")
            )


def evaluate_places(card: ModelCard, onnx, inputs: EvalInputs):
    """Place-recognition Recall@N of the export and the torch reference over query drives against
    database drives, or of the export against a place map's windows (``--map``, made by
    ``radaredge map build``) (:func:`radaredge.eval.places.evaluate`)."""
    sides = ("map", "queries") if inputs.map is not None and inputs.database is None else ("database", "queries")
    inputs.require(
        "place recognition (against --database drives or a --map from `radaredge map build`)",
        sides,
        card.name,
        ("checkpoint", "radius", "reference"),
    )
    return evaluate(
        card,
        onnx,
        inputs.database,
        inputs.queries,
        inputs.checkpoint,
        inputs.radius,
        inputs.reference,
        inputs.progress,
        map_dir=inputs.map,
    )


def evaluate_localisation(card: ModelCard, onnx, inputs: EvalInputs):
    """Table I (localisation recall) and Table II (cell-retrieval recall) of the export, and of the
    torch reference unless ``--no-reference``, over the cell maps at ``--map``
    (:func:`radaredge.eval.localisation.evaluate_localization`)."""
    inputs.require("localisation recall", ("map",), card.name, ("checkpoint", "reference"))
    return localize(
        onnx,
        inputs.map,
        progress=inputs.progress,
        model=card.name,
        reference=inputs.reference,
        checkpoint=inputs.checkpoint,
    )


def evaluate_detections(card: ModelCard, onnx, inputs: EvalInputs):
    """3D / BEV AP and AOS per class and area of the torch reference, the export, its int8 copy
    and OpenVINO over a labelled split (:func:`radaredge.eval.detection.evaluate_detection`)."""
    inputs.require("3D-detection AP", ("data",), card.name, ("checkpoint", "reference", "split", "dataset"))
    return evaluate_detection(
        card,
        onnx,
        inputs.data,
        inputs.split,
        inputs.checkpoint,
        inputs.reference,
        inputs.dataset,
        progress=inputs.progress,
    )


# evaluation name (ModelSpec.evaluation) -> fn(card, onnx, EvalInputs) -> a report
EVALUATIONS: dict[str, Callable] = {
    "place recognition": evaluate_places,
    "localisation": evaluate_localisation,
    "detection": evaluate_detections,
}


# With ``parity-check --quantized``: the int8 graph judged by the model's task metric as well, by
# evaluation name, fn(card, onnx path, checkpoint) -> a report with lines(), to_dict() and a truth value.
QUANTIZED_TASKS: dict[str, Callable] = {
    "detection": int8_ap_loss,
}
