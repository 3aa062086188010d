"""Issue 47: the console of module 6's CPU recipe (random weights, ``max_minutes`` set, nothing else), read by a
breeder who never opened a config. Every WARNING line names something the user can and should change; the recipe's
own choices (all backbone stages trained from random weights, the budget ending a run of 1000 ceiling epochs) are
information; the progress lines keep one form ("epoch N", the number that fit changes as the pace is measured);
the last line speaks of the iterations done, not of the recipe's 1000 epochs."""

from __future__ import annotations

import logging
import re

import pytest

from matchplant.core.runtime.config import load_config
from matchplant.model_train.config import ModelTrainConfig
from matchplant.model_train.run import train

pytestmark = pytest.mark.usefixtures("torch_one_thread")

# the words of a line about something the user set and can change; a warning line must hold one of them
USER_SETTINGS = re.compile(r"\b(max_minutes|epochs|val_json|val|warmup_iters|trainable_backbone_layers|split)\b")


@pytest.fixture(scope="module")
def console(train_tiles, tmp_path_factory):
    """A short CPU recipe run: what it logged, and its summary."""
    out = tmp_path_factory.mktemp("recipe")
    cfg = load_config(
        ModelTrainConfig,
        None,
        [
            f"train_json={train_tiles[0]}",
            f"val_json={train_tiles[1]}",
            f"output_dir={out}",
            "model.pretrained=none",  # what auto picks offline (pretrained: auto would ask the network)
            "model.min_size=128",
            "model.max_size=128",
            "batch_size=2",
            "num_workers=0",
            "max_minutes=0.25",
        ],
    )
    records: list[logging.LogRecord] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record)

    handler = Keep(level=logging.INFO)
    logger = logging.getLogger("matchplant")
    level = logger.level
    logger.addHandler(handler)
    logger.setLevel(logging.INFO)
    try:
        summary = train(cfg)
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
    return records, summary


def test_every_warning_names_a_setting_the_user_can_change(console):
    records, _ = console
    warnings = [r.getMessage() for r in records if r.levelno >= logging.WARNING]
    for text in warnings:
        assert USER_SETTINGS.search(text), f"a warning about nothing the user set: {text}"
    said = "\n".join(warnings)
    assert "pretrained is none" not in said and "lower epochs" not in said and "shorter than one iteration" not in said


def test_the_recipes_choices_are_information(console):
    records, _ = console
    infos = "\n".join(r.getMessage() for r in records if r.levelno == logging.INFO)
    assert "epochs: 1000" in infos and "max_minutes = 0.25 sets the run's length" in infos, infos


def test_the_progress_lines_keep_one_form_and_the_last_line_speaks_of_what_was_done(console):
    records, summary = console
    epochs = [r.getMessage() for r in records if re.match(r"epoch \d+", r.getMessage())]
    assert epochs and not any(re.match(r"epoch \d+/\d+", e) for e in epochs), epochs
    assert summary["status"].startswith(("stopped_by_max_minutes", "finished")), summary["status"]
    assert "of 1000 epochs" not in summary["message"] and "9000" not in summary["message"], summary["message"]
