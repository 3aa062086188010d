"""``matchplant init PROJECT``: write a commented pipeline.yaml for a season from an ODM project folder."""

from pathlib import Path

from matchplant.core.formats.coco import read_dataset
from matchplant.detection.foreign import read_any_checkpoint
from matchplant.detection.objects import box_sizes, recommend, size_stats
from matchplant.pipeline.season import InitConfig, init_pipeline
from matchplant.steps import StepSpec


def advise(annotations: Path) -> dict:
    """``matchplant inspect``'s advice for the annotated photos: tile size, overlap, the detector's input size."""
    ds = read_dataset(annotations, validate=False)
    sizes = sorted({(int(im["width"]), int(im["height"])) for im in ds.get("images", [])})
    return recommend(size_stats(*box_sizes(ds)), sizes)


def checkpoint_kind(path: Path) -> None:
    """Raise when ``path`` is no detector MatchPlant reads (a YOLO best.pt, another program's file, a damaged one)."""
    read_any_checkpoint(path, fit_classes=False)


SPEC = StepSpec(
    name="init",
    config=InitConfig,
    run=lambda cfg: init_pipeline(cfg, advise, checkpoint_kind),
    output_key=None,
    positional_key="project",
    flags={
        "--annotations": ("annotations", "plant boxes on the project's photos (COCO JSON): train a detector"),
        "--checkpoint": ("checkpoint", "a trained detector (best.pt): detect with it"),
        "--output": ("output", 'the pipeline file to write (default pipeline.yaml; "-": standard output)'),
        "--project-type": ("project_type", "auto, odm, metashape or pix4d"),
    },
)
