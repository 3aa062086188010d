"""Module 7 (model_test): checkpoints that are not MatchPlant's (bare weights, truncated, text, edited to another
architecture), test tiles that do not fit the files or the model, image folders without images, settings that
cannot work (overlap, device), a run that finds nothing; and the inputs that must work (a single image, paths
with spaces and non-ASCII letters, junk files, a tile larger than the image, a BOM/CRLF JSON from Windows).

Everything runs on the artifacts' untrained checkpoint (``model.pt``) and on tiny images (128 px crops of the
tiny field's undistorted photos, or two of module 5's test tiles), so each case takes a few seconds. The
must-work checks hold the outputs to the inputs: one predictions entry per image with its name and true size,
every box inside its image; the metrics count the test tiles and plants the JSON holds.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import torch
from harness import Case, Work
from PIL import Image

TILE = ("detect.tile_size=128", "detect.overlap=32", "device=cpu")


def args(w: Work, checkpoint: Path, *extra: str) -> list[str]:
    a = ["--set", f"checkpoint={checkpoint}", "--set", f"output_dir={w.out}"]
    for e in extra:
        a += ["--set", e]
    return a


def photo(w: Work, folder: Path, name: str, index: int = 1, size: int = 128) -> Path:
    """A ``size`` px crop of the tiny field's undistorted photo ``index``, saved as ``folder/name``."""
    src = w.artifacts / "field" / "opensfm" / "undistorted" / "images" / f"SIM_{index:04d}.JPG.tif"
    folder.mkdir(parents=True, exist_ok=True)
    with Image.open(src) as im:
        im.convert("RGB").crop((60, 40, 60 + size, 40 + size)).save(folder / name)
    return folder / name


def photos(w: Work, name: str = "photos", n: int = 2) -> Path:
    folder = w.inputs / name
    for i in range(1, n + 1):
        photo(w, folder, f"SIM_{i:04d}.JPG", i)
    return folder


def detect_args(w: Work, images: Path, *extra: str, checkpoint: Path | None = None) -> list[str]:
    return args(w, checkpoint or w.copy("model.pt"), f"detect.images={images}", *TILE, *extra)


def tiles_subset(w: Work, n: int = 2, folder: str = "tiles", split: str = "test") -> tuple[Path, dict]:
    """The first ``n`` tiles of a split of module 5 (JSON and images, in module 5's layout: ``<split>.json``
    beside ``<split>/images/``)."""
    data = json.loads((w.artifacts / "tiles" / f"{split}.json").read_text())
    data["images"] = data["images"][:n]
    keep = {im["id"] for im in data["images"]}
    data["annotations"] = [a for a in data["annotations"] if a["image_id"] in keep]
    root = w.inputs / folder
    (root / split / "images").mkdir(parents=True)
    for im in data["images"]:
        shutil.copy2(w.artifacts / "tiles" / split / "images" / im["file_name"], root / split / "images")
    path = root / f"{split}.json"
    path.write_text(json.dumps(data))
    return path, data


def eval_args(w: Work, dataset: Path, *extra: str, checkpoint: Path | None = None) -> list[str]:
    return args(
        w,
        checkpoint or w.copy("model.pt"),
        f"evaluate.dataset_json={dataset}",
        "device=cpu",
        "evaluate.drawn_images=1",
        *extra,
    )


def edited_checkpoint(w: Work, edit) -> Path:
    data = torch.load(w.artifacts / "model.pt", map_location="cpu", weights_only=False)
    edit(data)
    path = w.inputs / "model.pt"
    torch.save(data, path)
    return path


# -- checks --------------------------------------------------------------------------------------------------


def predictions_for(*names_sizes: tuple[str, int, int]):
    """predictions.json lists exactly these images (name, width, height), each box inside its image."""

    def check(w: Work) -> None:
        data = json.loads((w.out / "predictions.json").read_text())
        assert [(im["file_name"], im["width"], im["height"]) for im in data["images"]] == list(names_sizes)
        size = {im["id"]: (im["width"], im["height"]) for im in data["images"]}
        assert data["predictions"], "the untrained model finds boxes at score 0.3 on the tiny field's photos"
        for p in data["predictions"]:
            x, y, bw, bh = p["bbox"]
            W, H = size[p["image_id"]]
            assert -0.01 <= x and -0.01 <= y and x + bw <= W + 0.01 and y + bh <= H + 0.01, p
        assert not any(p.name.startswith(".") for p in w.out.iterdir() if p.name != "logs"), list(w.out.iterdir())

    return check


def logged(text: str, then=None):
    """The run log holds a warning with ``text`` (and ``then`` holds too)."""

    def check(w: Work) -> None:
        if then is not None:
            then(w)
        log = "\n".join(p.read_text() for p in (w.out / "logs").glob("*.log"))
        assert any("WARNING" in ln and text in ln for ln in log.splitlines()), log[-3000:]

    return check


def metrics_for(n_images: int, json_name: str = "test.json"):
    """metrics.json scores the tiles and plants of the JSON given (counted here from the JSON itself)."""

    def check(w: Work) -> None:
        data = json.loads(next(w.inputs.rglob(json_name)).read_text(encoding="utf-8-sig"))
        m = json.loads((w.out / "metrics.json").read_text())
        assert m["images"] == n_images == len(data["images"]) and m["plants"] == len(data["annotations"]), m
        assert m["detections"] > 0 and 0 <= m["coco"]["AP50"] <= 1
        preds = json.loads((w.out / "test_predictions.json").read_text())
        assert sorted(im["file_name"] for im in preds["images"]) == sorted(im["file_name"] for im in data["images"])
        assert (w.out / "pr_curve.png").is_file()

    return check


# -- checkpoints ---------------------------------------------------------------------------------------------


def checkpoint_state_dict(w: Work) -> list[str]:
    data = torch.load(w.artifacts / "model.pt", map_location="cpu", weights_only=False)
    torch.save(data["model_state"], w.inputs / "fasterrcnn_weights.pth")
    return detect_args(w, photos(w), checkpoint=w.inputs / "fasterrcnn_weights.pth")


def checkpoint_truncated(w: Work) -> list[str]:
    path = w.copy("model.pt")
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    return detect_args(w, photos(w), checkpoint=path)


def checkpoint_empty(w: Work) -> list[str]:
    path = w.inputs / "best.pt"
    path.write_bytes(b"")
    return detect_args(w, photos(w), checkpoint=path)


def checkpoint_is_text(w: Work) -> list[str]:
    path = w.inputs / "best.pt"
    path.write_text("checkpoint: runs/train/checkpoints/best.pt\nepochs: 30\n")
    return detect_args(w, photos(w), checkpoint=path)


def checkpoint_other_architecture(w: Work) -> list[str]:
    """The settings say ResNet-50 but the weights are MobileNet's (an edited or mixed-up file)."""
    path = edited_checkpoint(w, lambda d: d["model_config"].update(architecture="fasterrcnn_resnet50_fpn"))
    return detect_args(w, photos(w), checkpoint=path)


def checkpoint_unknown_architecture(w: Work) -> list[str]:
    path = edited_checkpoint(w, lambda d: d["model_config"].update(architecture="yolov8n"))
    return detect_args(w, photos(w), checkpoint=path)


def checkpoint_without_classes(w: Work) -> list[str]:
    path = edited_checkpoint(w, lambda d: d.pop("class_names"))
    return eval_args(w, tiles_subset(w)[0], checkpoint=path)


# -- detection inputs ----------------------------------------------------------------------------------------


def junk_only_folder(w: Work) -> list[str]:
    folder = w.inputs / "photos"
    folder.mkdir()
    (folder / "Thumbs.db").write_bytes(b"\x00junk")
    (folder / "._SIM_0001.JPG").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (folder / "flight notes.txt").write_text("flight 1")
    return detect_args(w, folder)


def parent_of_image_folder(w: Work) -> list[str]:
    photos(w, "flight/images")
    return detect_args(w, w.inputs / "flight")


def text_file_as_image(w: Work) -> list[str]:
    path = w.inputs / "image_list.txt"
    path.write_text("SIM_0001.JPG\n")
    return detect_args(w, path)


def truncated_photo(w: Work) -> list[str]:
    folder = photos(w, n=3)
    p = folder / "SIM_0002.JPG"
    p.write_bytes(p.read_bytes()[: p.stat().st_size // 2])
    return detect_args(w, folder)


def overlap_not_below_tile(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "detect.overlap=128"]


def nothing_found(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "detect.score_threshold=0.999"]


def device_cuda_without_cuda(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "device=cuda"]


def device_typo(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "device=gpu"]


def cover_without_project(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "detect.cover=2"]


def cover_project_of_other_photos(w: Work) -> list[str]:
    folder = w.inputs / "other"
    photo(w, folder, "plot_a.png")
    return [*detect_args(w, folder), "--set", "detect.cover=1", "--set", f"detect.project_dir={w.artifacts / 'field'}"]


def runtime_typo(w: Work) -> list[str]:
    return [*detect_args(w, photos(w)), "--set", "detect.runtime=openvino"]


def output_is_image_folder(w: Work) -> list[str]:
    folder = photos(w)
    return [x if not x.startswith("output_dir=") else f"output_dir={folder}" for x in detect_args(w, folder)]


# -- evaluation inputs ---------------------------------------------------------------------------------------


def eval_other_categories(w: Work) -> list[str]:
    path, data = tiles_subset(w)
    data["categories"] = [{"id": 1, "name": "weed", "supercategory": "plant"}]
    path.write_text(json.dumps(data))
    return eval_args(w, path)


def eval_no_annotations(w: Work) -> list[str]:
    path, data = tiles_subset(w)
    data["annotations"] = []
    path.write_text(json.dumps(data))
    return eval_args(w, path)


def eval_predictions_file(w: Work) -> list[str]:
    return eval_args(w, w.copy("predictions.json"))


def eval_tile_missing(w: Work) -> list[str]:
    path, data = tiles_subset(w)
    (path.parent / "test" / "images" / "SIM_0002.JPG_96_0.tif").unlink()
    return eval_args(w, path)


def eval_tile_truncated(w: Work) -> list[str]:
    path, data = tiles_subset(w)
    tile = path.parent / "test" / "images" / data["images"][0]["file_name"]
    tile.write_bytes(tile.read_bytes()[: tile.stat().st_size // 2])
    return eval_args(w, path)


def scaled_json(w: Work, factor: float, boxes: bool) -> Path:
    """The test subset with every image's width/height (and, with ``boxes``, every box) times ``factor``."""
    path, data = tiles_subset(w)
    for im in data["images"]:
        im["width"], im["height"] = int(im["width"] * factor), int(im["height"] * factor)
    if boxes:
        for a in data["annotations"]:
            a["bbox"] = [v * factor for v in a["bbox"]]
            a["area"] = a["bbox"][2] * a["bbox"][3]
    path.write_text(json.dumps(data))
    return path


def eval_sizes_boxes_outside(w: Work) -> list[str]:
    return eval_args(w, scaled_json(w, 2, boxes=True))


def eval_sizes_differ_boxes_inside(w: Work) -> list[str]:
    return eval_args(w, scaled_json(w, 2, boxes=False))


def eval_bom_crlf_windows_names(w: Work) -> list[str]:
    """A JSON saved on Windows: BOM, CRLF line ends, file names with backslashes; in a folder with spaces."""
    path, data = tiles_subset(w, folder="test tiles (copy)")
    for im in data["images"]:
        im["file_name"] = "images\\" + im["file_name"]
    text = json.dumps(data, indent=1).replace("\n", "\r\n")
    path.write_bytes(b"\xef\xbb\xbf" + text.encode())
    return eval_args(w, path)


# -- must work: detection ------------------------------------------------------------------------------------


# the untrained checkpoint scores its boxes just under 0.5 on these crops: must-work runs keep boxes from 0.3
FOUND = "detect.score_threshold=0.3"


def single_image_file(w: Work) -> list[str]:
    return detect_args(w, photo(w, w.inputs / "photos", "SIM_0003.JPG", 3), FOUND)


def unicode_paths_and_junk(w: Work) -> list[str]:
    folder = photos(w, "fotos ñandú 2024")
    (folder / "Thumbs.db").write_bytes(b"\x00junk")
    (folder / "._SIM_0001.JPG").write_bytes(b"\x00\x05\x16\x07 resource fork")
    (folder / "desktop.ini").write_text("[.ShellClassInfo]\r\n")
    return detect_args(w, folder, FOUND, checkpoint=w.copy("model.pt", "modèle v1.pt"))


def tile_larger_than_image(w: Work) -> list[str]:
    folder = w.inputs / "photos"
    photo(w, folder, "SIM_0004.tif", 4, size=100)
    return args(w, w.copy("model.pt"), f"detect.images={folder}", "device=cpu", FOUND)  # tile 1024, overlap 256


CUDA_SKIP = (pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here"),)

CASES = [
    # checkpoints
    Case(
        "m7-checkpoint-bare-state-dict",
        "model_test",
        checkpoint_state_dict,
        mentions=("fasterrcnn_weights.pth", "state_dict"),
    ),
    Case("m7-checkpoint-truncated", "model_test", checkpoint_truncated, mentions=("model.pt", "truncated")),
    Case("m7-checkpoint-empty", "model_test", checkpoint_empty, mentions=("best.pt", "empty")),
    Case("m7-checkpoint-is-text", "model_test", checkpoint_is_text, mentions=("best.pt", "text file")),
    Case(
        "m7-checkpoint-other-architecture",
        "model_test",
        checkpoint_other_architecture,
        mentions=("model.pt", "fasterrcnn_resnet50_fpn", "do not fit"),
    ),
    Case(
        "m7-checkpoint-unknown-architecture",
        "model_test",
        checkpoint_unknown_architecture,
        mentions=("model.pt", "yolov8n"),
    ),
    Case(
        "m7-checkpoint-without-classes", "model_test", checkpoint_without_classes, mentions=("model.pt", "class_names")
    ),
    # detection inputs and settings
    Case("m7-detect-folder-junk-only", "model_test", junk_only_folder, mentions=("photos", "Thumbs.db", "notes.txt")),
    Case(
        "m7-detect-parent-of-image-folder",
        "model_test",
        parent_of_image_folder,
        mentions=("flight", "did you mean", "images"),
    ),
    Case(
        "m7-detect-text-file-as-image", "model_test", text_file_as_image, mentions=("image_list.txt", "detect.images")
    ),
    Case("m7-detect-truncated-photo", "model_test", truncated_photo, mentions=("SIM_0002.JPG", "truncated")),
    Case(
        "m7-overlap-not-below-tile",
        "model_test",
        overlap_not_below_tile,
        mentions=("detect.overlap", "detect.tile_size"),
    ),
    Case("m7-nothing-found", "model_test", nothing_found, mentions=("detect.score_threshold", "best box", "0.999")),
    Case("m7-device-cuda-without-cuda", "model_test", device_cuda_without_cuda, mentions=("cuda",), marks=CUDA_SKIP),
    Case("m7-device-typo", "model_test", device_typo, mentions=("device", "gpu")),
    Case("m7-cover-without-project", "model_test", cover_without_project, mentions=("detect.project_dir", "photos")),
    Case(
        "m7-cover-project-of-other-photos",
        "model_test",
        cover_project_of_other_photos,
        mentions=("detect.project_dir", "none of the 1 photo(s)"),
    ),
    Case("m7-runtime-typo", "model_test", runtime_typo, mentions=("detect.runtime", "openvino", "onnx")),
    Case("m7-output-is-image-folder", "model_test", output_is_image_folder, mentions=("output_dir", "detect.images")),
    # evaluation inputs
    Case("m7-eval-other-categories", "model_test", eval_other_categories, mentions=("test.json", "weed", "model.pt")),
    Case("m7-eval-no-annotations", "model_test", eval_no_annotations, mentions=("test.json", "no annotations")),
    Case(
        "m7-eval-predictions-file",
        "model_test",
        eval_predictions_file,
        mentions=("predictions.json", "predictions file"),
    ),
    Case("m7-eval-tile-missing", "model_test", eval_tile_missing, mentions=("test.json", "SIM_0002.JPG_96_0.tif")),
    Case("m7-eval-tile-truncated", "model_test", eval_tile_truncated, mentions=("SIM_0002.JPG_0_0.tif", "truncated")),
    Case(
        "m7-eval-sizes-boxes-outside",
        "model_test",
        eval_sizes_boxes_outside,
        mentions=("test.json", "outside", "256x256", "128x128"),
    ),
    # must work
    Case(
        "m7-single-image-file",
        "model_test",
        single_image_file,
        expect="ok",
        check=predictions_for(("SIM_0003.JPG", 128, 128)),
    ),
    Case(
        "m7-unicode-paths-and-junk",
        "model_test",
        unicode_paths_and_junk,
        expect="ok",
        check=predictions_for(("SIM_0001.JPG", 128, 128), ("SIM_0002.JPG", 128, 128)),
    ),
    Case(
        "m7-tile-larger-than-image",
        "model_test",
        tile_larger_than_image,
        expect="ok",
        check=logged("larger than 1 of the 1 image", predictions_for(("SIM_0004.tif", 100, 100))),
    ),
    Case(
        "m7-eval-bom-crlf-windows-names", "model_test", eval_bom_crlf_windows_names, expect="ok", check=metrics_for(2)
    ),
    Case(
        "m7-eval-sizes-differ-boxes-inside",
        "model_test",
        eval_sizes_differ_boxes_inside,
        expect="ok",
        check=logged("other width/height", metrics_for(2)),
    ),
]
