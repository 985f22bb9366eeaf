"""Which recipe trains each model, keyed by model family name, and what ``train`` was given."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

from ..cards import ModelCard
from ..data.bag_drives import BagSource
from ..errors import ConfigError
from .des4pos import TextRecipe, train_text as run_text
from .maffnet_head import train_head
from .run import no_progress
from .tdfanet import PlaceRecipe, train_places as run_places


@dataclass(frozen=True)
class TrainInputs:
    """What ``train`` was given besides the card, the model and the data: the run directory
    ``output``, ``device`` (cpu or cuda), ``resume`` from ``output``'s last state, the held-out
    ``validation`` drives or scenes (None: the model's default split), the scan ``data_format``,
    where ROS bags keep their scans and fixes (``bag``: the fields of
    :class:`radaredge.data.bag_drives.BagSource`), the recipe ``options`` (name -> value, None =
    the recipe's default), and the progress-bar factory ``progress(desc, total)`` and ``log(line)``."""

    output: str
    device: str = "cpu"
    resume: bool = False
    validation: tuple[str, ...] | None = None
    data_format: str | None = None
    bag: dict | None = None
    options: dict | None = None
    progress: Callable | None = None
    log: Callable[[str], None] | None = None


def train_places(card: ModelCard, model, data, inputs: TrainInputs):
    """TDFANet's training recipe (:mod:`radaredge.train.tdfanet`) on the drives under ``data``."""
    recipe = PlaceRecipe.from_options(inputs.options or {})
    bag = BagSource(**{k: v for k, v in (inputs.bag or {}).items() if v is not None})
    return run_places(card, model, data, inputs.output, recipe, inputs.device, inputs.resume, inputs.validation,
                      inputs.data_format, inputs.progress or no_progress, inputs.log or (lambda line: None), bag)


def train_text(card: ModelCard, model, data, inputs: TrainInputs):
    """Des4Pos's training stages (:mod:`radaredge.train.des4pos`) on the cell maps under ``data``."""
    drive_only = [f"--{k.replace('_', '-')}" for k, v in (inputs.bag or {}).items() if v is not None]
    if inputs.data_format:
        drive_only.append("--format")
    if drive_only:
        raise ConfigError(f"{', '.join(drive_only)} describe radar drives; {card.name} trains on cell maps with "
                          f"described poses (`radaredge make-city`, KITTI360Pose cells/ + poses/)")
    recipe = TextRecipe.from_options(inputs.options or {})
    return run_text(card, model, data, inputs.output, recipe, inputs.device, inputs.resume, inputs.validation,
                    inputs.progress or no_progress, inputs.log or (lambda line: None))


RECIPES: dict[str, Callable] = {
    "tdfanet": train_places,
    "des4pos": train_text,
    "maffnet": train_head,
}
