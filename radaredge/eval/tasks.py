"""Which task evaluates each model, keyed by model family name, and what ``eval`` was given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..cards import ModelCard
from ..errors import ConfigError
from .localisation import evaluate_localization as localize
from .places import evaluate


@dataclass(frozen=True)
class EvalInputs:
    """What ``eval`` was given; each model's task (:data:`EVALUATIONS`) takes what it needs and
    refuses the rest. Place recognition: ``database``/``queries`` drives, ``radius`` (m),
    ``checkpoint`` and ``reference``; localisation: a cell ``map``."""

    database: str | None = None
    queries: str | None = None
    map: str | None = None
    checkpoint: str | None = None
    radius: float = 5.0
    reference: bool = True
    progress: Callable | None = None

    def require(self, task: str, needed: tuple[str, ...], card_name: str, uses: tuple[str, ...] = ()) -> None:
        """ConfigError unless exactly the inputs ``needed`` (of database, queries, map) are given
        and no option outside ``uses`` (of checkpoint, radius, reference) was set."""
        missing = [n for n in needed if getattr(self, n) is None]
        extra = [n for n in ("database", "queries", "map") if n not in needed and getattr(self, n) is not None]
        options = (("checkpoint", "checkpoint", self.checkpoint is not None), ("radius", "radius", self.radius != 5.0),
                   ("reference", "no-reference", not self.reference))       # (name, option, set)
        extra += [option for name, option, given in options if given and name not in uses]
        if missing or extra:
            raise ConfigError(f"{card_name} is evaluated by {task} on {', '.join('--' + n for n in needed)}"
                              + (f"; missing {', '.join('--' + n for n in missing)}" if missing else "")
                              + (f"; {', '.join('--' + n for n in extra)} not used" if extra else ""))


def evaluate_places(card: ModelCard, onnx, inputs: EvalInputs):
    """Place-recognition Recall@N of the export and the torch reference over query drives against
    database drives (:func:`radaredge.eval.places.evaluate`)."""
    inputs.require("place recognition", ("database", "queries"), card.name, ("checkpoint", "radius", "reference"))
    return evaluate(card, onnx, inputs.database, inputs.queries, inputs.checkpoint, inputs.radius, inputs.reference,
                    inputs.progress)


def evaluate_localisation(card: ModelCard, onnx, inputs: EvalInputs):
    """Table I (localisation recall) and Table II (cell-retrieval recall) of the export, and of the
    torch reference unless ``--no-reference``, over the cell maps at ``--map``
    (:func:`radaredge.eval.localisation.evaluate_localization`)."""
    inputs.require("localisation recall", ("map",), card.name, ("checkpoint", "reference"))
    return localize(onnx, inputs.map, progress=inputs.progress, model=card.name, reference=inputs.reference,
                    checkpoint=inputs.checkpoint)


EVALUATIONS: dict[str, Callable] = {
    "tdfanet": evaluate_places,
    "des4pos": evaluate_localisation,
}
