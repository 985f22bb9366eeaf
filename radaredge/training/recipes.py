"""The training recipes ``train`` runs, by the name a model's spec gives in ``recipe``, and what
``train`` was given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..cards import ModelCard
from ..data.bag_drives import BagSource
from ..errors import ConfigError
from ..progress import no_progress
from .des4pos import TextRecipe
from .des4pos import train_text as run_text
from .maffnet import VALIDATION_SPLIT, DetectionRecipe, train_detector
from .tdfanet import PlaceRecipe
from .tdfanet import train_places as run_places


@dataclass(frozen=True)
class TrainInputs:
    """What ``train`` was given besides the card, the model and the data: the run directory
    ``output``, the ``checkpoint`` the model's weights were loaded from (None: seeded),
    ``device`` (cpu or cuda), ``resume`` from ``output``'s last state, the held-out
    ``validation`` drives, scenes or split (None: the model's default), the scan ``data_format``,
    where ROS bags keep their scans and fixes (``bag``: the fields of
    :class:`radaredge.data.bag_drives.BagSource`), the recipe ``options`` (name -> value, None =
    the recipe's default), and the progress-bar factory ``progress(desc, total)`` and ``log(line)``."""

    output: str
    checkpoint: str | None = None
    device: str = "cpu"
    resume: bool = False
    validation: tuple[str, ...] | None = None
    data_format: str | None = None
    bag: dict | None = None
    options: dict | None = None
    progress: Callable | None = None
    log: Callable[[str], None] | None = None


def train_places(card: ModelCard, model, data, inputs: TrainInputs):
    """TDFANet's training recipe (:mod:`radaredge.training.tdfanet`) on the drives under ``data``."""
    recipe = PlaceRecipe.from_options(inputs.options or {})
    bag = BagSource(**{k: v for k, v in (inputs.bag or {}).items() if v is not None})
    return run_places(
        card,
        model,
        data,
        inputs.output,
        recipe,
        inputs.device,
        inputs.resume,
        inputs.validation,
        inputs.data_format,
        inputs.progress or no_progress,
        inputs.log or (lambda line: None),
        bag,
        inputs.checkpoint,
    )


def train_text(card: ModelCard, model, data, inputs: TrainInputs):
    """Des4Pos's training stages (:mod:`radaredge.training.des4pos`) on the cell maps under ``data``."""
    drive_only = [f"--{k.replace('_', '-')}" for k, v in (inputs.bag or {}).items() if v is not None]
    if inputs.data_format:
        drive_only.append("--format")
    if drive_only:
        raise ConfigError(
            f"{', '.join(drive_only)} describe radar drives; {card.name} trains on cell maps with "
            f"described poses (`radaredge make-city`, KITTI360Pose cells/ + poses/)"
        )
    recipe = TextRecipe.from_options(inputs.options or {})
    return run_text(
        card,
        model,
        data,
        inputs.output,
        recipe,
        inputs.device,
        inputs.resume,
        inputs.validation,
        inputs.progress or no_progress,
        inputs.log or (lambda line: None),
    )


def train_maffnet(card: ModelCard, model, data, inputs: TrainInputs):
    """MAFF-Net (one stage or two) with upstream's recipe (:mod:`radaredge.training.maffnet`) on the labelled
    KITTI-layout set under ``data`` (VoD or TJ4DRadSet; ``--validation`` names the split)."""
    drive_only = [f"--{k.replace('_', '-')}" for k, v in (inputs.bag or {}).items() if v is not None]
    if drive_only:
        raise ConfigError(
            f"{', '.join(drive_only)} describe ROS bag drives; {card.name} trains on a labelled "
            f"View-of-Delft or TJ4DRadSet layout (`radaredge make-benchmark --task detection`)"
        )
    if inputs.validation is not None and len(inputs.validation) != 1:
        raise ConfigError(
            f"--validation: {card.name} validates on one split of the set (e.g. val), got {list(inputs.validation)}"
        )
    if inputs.data_format == "transloc":
        raise ConfigError("--format transloc: MAFF-Net trains on View-of-Delft (vod) or TJ4DRadSet (tj4d) scans")
    recipe = DetectionRecipe.from_options(inputs.options or {})
    return train_detector(
        card,
        model,
        data,
        inputs.output,
        recipe,
        inputs.device,
        inputs.resume,
        inputs.validation[0] if inputs.validation else VALIDATION_SPLIT,
        inputs.data_format,
        inputs.checkpoint,
        inputs.progress or no_progress,
        inputs.log or (lambda line: None),
    )


# recipe name (ModelSpec.recipe) -> fn(card, model, data, TrainInputs) -> TrainReport
RECIPES: dict[str, Callable] = {
    "places": train_places,  # TDFANet: windows of drives, triplets by position
    "text-to-cells": train_text,  # Des4Pos: cell maps with described poses
    "openpcdet-detection": train_maffnet,  # MAFF-Net: a labelled KITTI-layout set
}
