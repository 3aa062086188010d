"""The demo table of docs/demo.md and the docs/ figures are written from a demo run's summary, not by hand."""

from __future__ import annotations

import json

import numpy as np
from PIL import Image

from matchplant.demo import DEMO_PAGE, TABLE_END, TABLE_START, demo_table, update_docs

SUMMARY = {
    "detector": {"coco": {"AP50": 0.8812, "AP": 0.3104}},
    "training": {"epochs_done": 2},
    "projection": {"share_matched": 0.991, "share_iou_above_0.5": 0.962, "iou_median": 0.871},
    "traits": {
        "plants": 1300,
        "true_plants": 1292,
        "height_r": 0.9991,
        "height_box_r": 0.963,
        "ndvi_r": 0.998,
        "ndvi_box_r": 0.32,
        "outline_iou_median": 0.897,
    },
    "plots": {"plots": 63, "stand_count_exact_share": 62 / 63, "gaps_found_share": 1.0, "false_gap_share": 0.0},
    "growth": {"reused_box_centre_error_median_m": 0.0427, "recentred_error_median_m": 0.0044},
}


def test_table_shows_the_run_figures():
    table = demo_table(SUMMARY)
    for text in (
        "AP50 88.1%",
        "AP 31.0%",
        "2 epochs",
        "99.1%",
        "96.2%",
        "median IoU 0.87",
        "1300 records for 1292",
        "over the canopy 0.999",
        "over the box 0.963",
        "box mean 0.320",
        "median IoU 0.90",
        "98.4% of 63 plots",
        "0.043 m",
        "0.004 m",
    ):
        assert text in table, (text, table)
    assert "n/a" in demo_table({})  # a missing figure says so instead of inventing one


def test_update_docs_rewrites_only_the_table_and_copies_the_figures(tmp_path):
    out, root = tmp_path / "demo_output", tmp_path / "repo"
    (out / "report").mkdir(parents=True)
    (out / "report" / "summary.json").write_text(json.dumps(SUMMARY))
    (out / "8_plants").mkdir()
    Image.fromarray(np.full((20, 30, 4), 200, np.uint8)).save(out / "8_plants" / "evaluation.png")
    (root / "docs").mkdir(parents=True)
    (root / DEMO_PAGE).write_text(f"before\n{TABLE_START}\nold table\n{TABLE_END}\nafter\n")
    update_docs(out, root)
    text = (root / DEMO_PAGE).read_text()
    assert text.startswith(f"before\n{TABLE_START}\n| | |") and text.endswith(f"{TABLE_END}\nafter\n")
    assert "old table" not in text and "AP50 88.1" in text
    with Image.open(root / "docs" / "evaluation.jpg") as im:
        assert im.format == "JPEG" and im.size == (30, 20)
    assert not (root / "docs" / "coverage.jpg").exists()  # the run made no coverage map: nothing is invented


NOISY = {
    "traits": {"height_r": 0.912, "ndvi_r": 0.871, "outline_iou_median": 0.61, "height_box_r": 0.9},
    "plots": {"plots": 63, "stand_count_exact_share": 0.5},
    "projection": {"share_matched": 0.95},
}


def test_table_puts_the_realistic_field_beside_the_exact_one_and_says_what_was_scored():
    held = {"photos": [f"SIM_{i:04d}.JPG.tif" for i in range(31)], "training_photos_projected": 0}
    table = demo_table({**SUMMARY, "noisy": NOISY, "held_out": held})
    head, _rule, *rows = table.split("\n\n")[0].splitlines()
    assert head.count("|") == 4 and "realistic" in head  # a third column
    height = next(r for r in rows if r.startswith("| plant height"))
    assert "over the canopy 0.999" in height and "over the canopy 0.912" in height
    assert "median IoU 0.61" in table and "stand count exact on 50.0% of 63" in table and "0.871" in table
    assert "31 photos the detector never saw" in table and "training photos projected: 0" in table
    assert "Reproducibility:" in table and "thread count" in table
    failed = demo_table({**SUMMARY, "noisy": {"error": "module 9 refused band 3"}})
    assert "Realistic field not measured: module 9 refused band 3" in failed
    assert demo_table(SUMMARY).startswith("| | |\n")  # without --noise realistic: the one-column table


def test_held_out_photos_leave_out_the_train_and_val_splits(tmp_path):
    from matchplant.demo import held_out_photos, link_photos

    summary = {
        "splits": {
            "train": {"source_images": ["b.tif", "d.tif"]},
            "val": {"source_images": ["c.tif"]},
            "test": {"source_images": ["e.tif"]},
        }
    }
    photos = ["a.tif", "b.tif", "c.tif", "d.tif", "e.tif", "f.tif"]
    held, splits = held_out_photos(summary, photos)
    assert held == ["a.tif", "e.tif", "f.tif"] and splits["train"] == ["b.tif", "d.tif"]
    src, dst = tmp_path / "src", tmp_path / "held"
    src.mkdir()
    for p in photos:
        (src / p).write_bytes(p.encode())
    dst.mkdir()
    (dst / "b.tif").write_bytes(b"stale")  # a training photo left from an earlier split
    link_photos(src, held, dst)
    assert sorted(p.name for p in dst.iterdir()) == held and (dst / "a.tif").read_bytes() == b"a.tif"
    before = (dst / "a.tif").stat().st_mtime_ns
    link_photos(src, held, dst)
    assert (dst / "a.tif").stat().st_mtime_ns == before  # kept: step 7's fingerprint stays
