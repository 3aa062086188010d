"""ODM split-merge projects (docs/DESIGN.md §6) read as one project: modules 2, 3, 7 and 8 on the top folder.

The project is the ``tiny`` field rewritten by :mod:`matchplant.simfield.split` (the ``split`` preset does the
same to the ``small`` field): two submodels sharing a flight line, each in its own topocentric frame with its
own ``coords.txt``, a misalignment of a few centimetres, merged rasters at the top, exact truth.
"""

from __future__ import annotations

import logging
import shutil

import numpy as np
import pandas as pd
import pytest

from matchplant.core.formats.coco import read_dataset
from matchplant.core.formats.odm import ODMProject
from matchplant.core.geometry.frames import TopocentricFrame
from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import InputError
from matchplant.core.runtime.io import read_json, write_json
from matchplant.min_img_finder.config import MinImgFinderConfig
from matchplant.min_img_finder.run import MinImageFinder
from matchplant.min_img_finder.setcover import reachable_coverage
from matchplant.model_test.inputs import list_images
from matchplant.odm_runner.outputs import check_outputs
from matchplant.plant_projection.config import PlantProjectionConfig
from matchplant.plant_projection.evaluation import evaluate_boxes
from matchplant.plant_projection.merge import MERGE_TOLERANCE, merge_views
from matchplant.plant_projection.run import run as run_projection_step
from matchplant.plant_projection.settings import ProjectionSettings
from matchplant.plant_projection.views import (
    ACROSS_COLUMNS,
    BESIDE_CUT_COLUMNS,
    UNSEEN_COLUMNS,
    ProjectedViews,
    project_predictions,
)
from matchplant.simfield.layout import FieldPaths
from matchplant.simfield.split import split_field, split_lines


def _split_copy(src: FieldPaths, dst, **kw) -> FieldPaths:
    shutil.copytree(src.root, dst)
    return split_field(FieldPaths(dst), **kw)


@pytest.fixture(scope="module")
def split(tiny_field, tmp_path_factory) -> FieldPaths:
    return _split_copy(tiny_field, tmp_path_factory.mktemp("split") / "field")


def _truth_predictions(f: FieldPaths) -> dict:
    ds = read_dataset(f.boxes_undistorted, validate=False)
    return {
        "images": ds["images"],
        "categories": ds["categories"],
        "predictions": [dict(a, score=1.0) for a in ds["annotations"]],
    }


def test_split_lines_share_one_line():
    assert split_lines(3, 2) == [[0, 1], [1, 2]]
    assert split_lines(5, 2) == [[0, 1, 2], [2, 3, 4]]
    assert split_lines(7, 3) == [[0, 1, 2], [2, 3, 4], [4, 5, 6]]


def test_layout_is_odm_split_merge(split):
    root = split.root
    assert not (root / "opensfm" / "reconstruction.json").exists()
    for name in ("submodel_0000", "submodel_0001"):
        sub = root / "submodels" / name
        for rel in (
            "opensfm/reconstruction.json",
            "opensfm/undistorted/reconstruction.json",
            "odm_georeferencing/coords.txt",
            "odm_dem/dsm.tif",
            "odm_orthophoto/odm_orthophoto.tif",
        ):
            assert (sub / rel).is_file(), rel
        assert any((sub / "opensfm/undistorted/images").iterdir())
    info = read_json(split.truth / "split.json")
    assert len(info["shared"]) == 3  # the shared flight line of the 3 x 3 flight
    refs = [s["reference_lla"]["latitude"] for s in info["submodels"]]
    assert refs[0] != refs[1]  # each submodel its own frame
    shifts = [np.hypot(*s["misalignment"]["translation_m"][:2]) for s in info["submodels"]]
    assert all(0.005 < d < 0.05 for d in shifts)


def test_reads_as_one_project_each_shot_in_its_own_frame(split, tiny_field, caplog):
    with caplog.at_level(logging.INFO, logger="matchplant"):
        project = ODMProject(split.root)
        ids = project.shot_ids()
    assert project.is_split and len(project.submodels) == 2
    assert "3 images appear in more than one submodel" in caplog.text
    single = ODMProject(tiny_field.root)
    assert ids == single.shot_ids() and set(project.undistorted_images()) == ids
    info = read_json(split.truth / "split.json")
    moves = {s["name"]: s["misalignment"] for s in info["submodels"]}
    for sid in sorted(ids):
        frame = project.frame_of(sid)
        assert isinstance(frame, TopocentricFrame)
        owner = project.owner(sid).name
        assert sid in next(s["images"] for s in info["submodels"] if s["name"] == owner)
        # the camera lands where the truth puts it, moved by its submodel's misalignment (a few cm)
        c = frame.to_map(project.shot(sid).center[None, :])[0]
        c_true = single.frame().to_map(single.shot(sid).center[None, :])[0]
        t = np.array(moves[owner]["translation_m"])
        assert np.linalg.norm(c - c_true - t) < 2e-3
    assert project.frame().crs.equals(single.frame().crs)
    with pytest.raises(InputError, match="one reconstruction per submodel"):
        project.reconstruction()


def test_pose_conversion_is_exact_without_misalignment(tiny_field, tmp_path):
    """Every pixel of every shot, through its submodel's topocentric frame, meets the map where the single
    project's does (independent of the projection code: points projected both ways)."""
    f = _split_copy(tiny_field, tmp_path / "exact", misalignment=0.0, rotation_deg=0.0)
    project, single = ODMProject(f.root), ODMProject(tiny_field.root)
    rng = np.random.default_rng(0)
    pts = np.column_stack([rng.uniform(0, 4, 200), rng.uniform(0, 3, 200), rng.uniform(0, 0.6, 200)])
    pts += [*single.coords[1][:2], 350.0]
    for sid in sorted(project.shot_ids()):
        uv_split = project.shot(sid).project(project.frame_of(sid).from_map(pts))
        uv_single = single.shot(sid).project(single.frame().from_map(pts))
        ok = np.isfinite(uv_single).all(axis=1)
        assert np.nanmax(np.abs(uv_split[ok] - uv_single[ok])) < 0.05  # pixels (the map's scale, ~1e-4, left)


@pytest.mark.slow
def test_projection_over_submodels_places_each_plant_once(split):
    preds = _truth_predictions(split)
    views, rejected = project_predictions(ODMProject(split.root), preds)
    assert len(rejected) == 0
    plants = merge_views(views)
    truth = pd.read_csv(split.map_boxes)
    m = evaluate_boxes(
        truth[["xmin", "ymin", "xmax", "ymax"]].to_numpy(), plants[["xmin", "ymin", "xmax", "ymax"]].to_numpy()
    )
    # issue 18's acceptance: each shot's boxes meet its own submodel's DSM and the submodels' views are aligned,
    # so only their common offset (a centimetre) remains: median IoU >= 0.9, no plant twice. Of tiny's 46 plants
    # 1 stays under IoU 0.5: seen only obliquely at the field's edge, its far sides are guesses. What the split
    # costs is not the misalignment (moving each submodel's poses and DSM by whole centimetres, without
    # resampling, scores as the single project) but the submodel DSMs resampled onto the moved grid, which round
    # thin plants' tops: rays then pass over them unnoticed (see the overshoot test below)
    assert m["share_matched"] == 1.0 and m["share_iou_above_0.5"] >= 0.95
    assert m["iou_median"] >= 0.9
    counts = plants["truth_plant_id"].value_counts()
    assert len(plants) == len(truth) and counts.max() == 1  # no plant twice (seen from two submodels)
    owners = views.table.groupby("truth_plant_id")["shot_id"].agg(
        lambda s: {ODMProject(split.root).owner(x).name for x in s}
    )
    assert (owners.map(len) == 2).any()  # some plants merged from views of both submodels


def _seam_side_errors(views, f: FieldPaths) -> np.ndarray:
    """For each whole view of a plant on the other submodel's side of the merged DSM (where the merged DSM holds
    the other submodel's surface): its sides minus its truth plant's, moved by its own submodel's misalignment."""
    t = views.table[~views.table["cut"]]
    subs = read_json(f.truth / "split.json")["submodels"]
    pivot = {s["name"]: np.array(s["misalignment"]["pivot"][:2]) for s in subs}
    move = {s["name"]: np.array(s["misalignment"]["translation_m"][:2]) for s in subs}
    truth = pd.read_csv(f.map_boxes).set_index("id").loc[t["truth_plant_id"], ["xmin", "ymin", "xmax", "ymax"]]
    centre = (truth[["xmin", "ymin"]].to_numpy() + truth[["xmax", "ymax"]].to_numpy()) / 2
    names = sorted(pivot)
    nearest = np.array(names)[np.argmin([np.hypot(*(centre - pivot[n]).T) for n in names], axis=0)]
    other = nearest != t["submodel"].to_numpy()
    shift = np.tile(np.array([move[s] for s in t["submodel"]]), 2)
    err = t[["xmin", "ymin", "xmax", "ymax"]].to_numpy() - truth.to_numpy() - shift
    return np.abs(err[other])


def test_each_shot_meets_its_own_submodels_dsm(split, tmp_path, caplog):
    """A submodel's poses and its own DSM are the same world moved by its misalignment, so its views land on the
    truth moved by it, on the other submodel's side of the seam too; the merged DSM (the other submodel's cells
    there) is used only for a submodel without a DSM (said in the log), or for every shot when 'dsm' is set."""
    preds = _truth_predictions(split)
    own, _ = project_predictions(ODMProject(split.root), preds)
    on_merged = ProjectionSettings.from_config(PlantProjectionConfig(dsm=split.root / "odm_dem" / "dsm.tif"))
    merged, _ = project_predictions(ODMProject(split.root), preds, on_merged)
    e_own, e_merged = _seam_side_errors(own, split), _seam_side_errors(merged, split)
    assert len(e_own) >= 50
    assert np.median(e_own) < 0.0025  # metres (1.9 mm; 3.1 mm on the merged DSM)
    assert np.median(e_own) < 0.75 * np.median(e_merged)
    broken = tmp_path / "no_dsm"
    shutil.copytree(split.root, broken)
    (broken / "submodels" / "submodel_0001" / "odm_dem" / "dsm.tif").unlink()
    with caplog.at_level(logging.INFO, logger="matchplant"):
        fallback, rejected = project_predictions(ODMProject(broken), preds)
    assert "submodel(s) submodel_0001 have no DSM of their own" in caplog.text
    assert len(rejected) == 0
    same = (fallback.table["submodel"] == "submodel_0000").to_numpy()
    assert same.any() and not same.all()
    np.testing.assert_array_equal(fallback.table["cx"].to_numpy()[same], own.table["cx"].to_numpy()[same])
    np.testing.assert_array_equal(fallback.table["cx"].to_numpy()[~same], merged.table["cx"].to_numpy()[~same])


def test_rays_that_leave_their_submodels_dsm_meet_the_merged_one(split, tmp_path, caplog):
    """ODM crops each submodel's DSM inside its reconstruction: an edge image's rays that leave it (or meet a hole
    in it) are projected on the merged DSM, so no box is lost; without a merged DSM they are reported."""
    import rasterio

    field = tmp_path / "cropped"
    shutil.copytree(split.root, field)
    own = field / "submodels" / "submodel_0000" / "odm_dem" / "dsm.tif"
    with rasterio.open(own) as src:
        data, profile = src.read(1), src.profile
    data[:, : data.shape[1] // 3] = -9999  # a third of it cut away, as a crop would
    with rasterio.open(own, "w", **profile) as dst:
        dst.write(data, 1)
    preds = _truth_predictions(split)
    with caplog.at_level(logging.INFO, logger="matchplant"):
        views, rejected = project_predictions(ODMProject(field), preds)
    assert "projected on the merged DSM" in caplog.text
    assert len(rejected) == 0 and len(views.table) == len(preds["predictions"])
    (field / "odm_dem" / "dsm.tif").unlink()
    _, lost = project_predictions(ODMProject(field), preds)
    assert len(lost) > 0 and set(lost["reason"]) <= {
        "ray meets the ground in a DSM nodata area",
        "ray leaves the DSM before reaching the ground",
    }


def test_module_8_needs_no_merged_dsm_when_every_submodel_has_its_own(split, tmp_path, caplog):
    """The step itself on a split run whose merge stage left no DSM at the top: every shot meets its own
    submodel's DSM, so nothing is missing and no 'covers only that submodel's part' warning is given."""
    field = tmp_path / "field"
    shutil.copytree(split.root, field)
    (field / "odm_dem" / "dsm.tif").unlink()
    write_json(tmp_path / "predictions.json", _truth_predictions(split))
    cfg = load_config(
        PlantProjectionConfig,
        None,
        [
            f"project={field}",
            f"predictions={tmp_path / 'predictions.json'}",
            f"output_dir={tmp_path / 'out'}",
            "mode=project",
        ],
    )
    with caplog.at_level(logging.INFO, logger="matchplant"):
        summary = run_projection_step(cfg)["projection"]
    assert "covers only" not in caplog.text
    assert summary["not_projected"] == 0 and summary["plants"] == len(pd.read_csv(split.map_boxes))


def test_module_3_selection_covers_the_whole_field(split, tiny_field, tmp_path):
    """The selection spans both submodels and covers what the whole flight covers (tiny's flight leaves a
    sixth of its orthophoto unseen, split or not)."""

    def finder(root):
        return MinImageFinder(
            load_config(
                MinImgFinderConfig,
                None,
                [f"project_dir={root}", "copy_images=none", f"output_dir={tmp_path / root.name}"],
            )
        )

    f, single = finder(split.root), finder(tiny_field.root)
    assert len(f.footprints) == 9
    assert {fp.frame is not None for fp in f.footprints} == {True}
    result = f.evaluate(f.select())
    reach = reachable_coverage(f.grid)
    assert reach == pytest.approx(reachable_coverage(single.grid), abs=0.005)
    assert result.exact_coverage >= min(0.95, reach) - 0.005
    owners = {ODMProject(split.root).owner(n).name for n in result.owned}
    assert owners == {"submodel_0000", "submodel_0001"}
    assert all(len(px) >= 3 for px in result.owned_pixels.values())


def test_module_2_checks_a_split_run(split, tmp_path, caplog):
    report = check_outputs(split.root)
    assert report.ok, report.problems
    assert report.details["split"]["images"] == 9
    assert report.details["split"]["images_in_several_submodels"] == 3
    assert set(report.details["split"]["submodels"]) == {"submodel_0000", "submodel_0001"}
    # the merged DSM missing: reported by module 2; the others fall back to a submodel's, said in the log
    broken = tmp_path / "broken"
    shutil.copytree(split.root, broken)
    (broken / "odm_dem" / "dsm.tif").unlink()
    (broken / "submodels" / "submodel_0001" / "opensfm" / "undistorted" / "images" / "SIM_0009.JPG.tif").unlink()
    report = check_outputs(broken)
    text = "\n".join(report.problems)
    assert "odm_dem/dsm.tif (the merged" in text and "submodels/submodel_0001: 1 of" in text
    with caplog.at_level(logging.WARNING, logger="matchplant"):
        path = ODMProject(broken).path("dsm")
    assert "submodel_0000" in str(path) and "merged digital surface model missing" in caplog.text


def test_module_7_lists_every_submodels_images_once(split):
    files = list_images(split.root)
    assert sorted(p.name for p in files) == sorted(f"{s}.tif" for s in ODMProject(split.root).shot_ids())


def _views(rows: list[dict]) -> ProjectedViews:
    """Projected views made by hand (map boxes, off-nadir angle, unseen sides and sides seen across the plant as
    strings of w, s, e, n): the merge's inputs, where each view's truth is known exactly."""
    t = pd.DataFrame(
        [
            {
                "xmin": r["box"][0],
                "ymin": r["box"][1],
                "xmax": r["box"][2],
                "ymax": r["box"][3],
                "off_nadir_deg": r["off_nadir"],
                "image_id": r["image"],
                "shot_id": f"SIM_{r['image']:04d}.JPG",
                "undistorted": True,
                "submodel": r.get("submodel", "submodel_0000"),
                "cut": False,
                "category_id": 1,
                "category": "plant",
                "score": 1.0,
                "source_image": f"SIM_{r['image']:04d}",
                "u1": 0.0,
                "v1": 0.0,
                "u2": 10.0,
                "v2": 10.0,
                "z": 0.0,
                "truth_plant_id": r["plant"],
                **{c: side in r.get("unseen", "") for c, side in zip(UNSEEN_COLUMNS, "wsen")},
                **{c: False for c in BESIDE_CUT_COLUMNS},
                **{c: side in r.get("across", "") for c, side in zip(ACROSS_COLUMNS, "wsen")},
            }
            for r in rows
        ]
    )
    t["cx"], t["cy"] = (t["xmin"] + t["xmax"]) / 2, (t["ymin"] + t["ymax"]) / 2
    t["area_m2"] = (t["xmax"] - t["xmin"]) * (t["ymax"] - t["ymin"])
    n = len(t)
    return ProjectedViews(t, np.zeros((n, 1, 3), np.float32), np.zeros((n, 3)), np.arange(n), None)


def test_a_seen_side_beyond_every_guess_of_it_is_an_overshoot():
    """A thin plant (40 x 10 cm) at the edge of what the flight saw, seen from the south only, by views of two
    submodels: its north side is hidden behind its top in the nearest-nadir view (a guess, mirrored about its top);
    in two views of the other submodel a ray passed over its top unnoticed (a DSM that rounds a thin top) and
    landed on the soil 17 cm beyond, taken for its edge. A side seen across the plant can only overshoot, so when
    the views that saw it (all across the plant) place it beyond every whole view's guess of it, the
    representative's guess stands; a side some view saw from its own side (a leaf tip on the soil) is trusted."""
    truth = (0.0, 0.0, 0.4, 0.1)

    def plant(north_seen_by_b: float, guess: float, across: str = "n") -> pd.Series:
        views = _views(
            [
                {"box": (0.0, 0.0, 0.4, guess), "off_nadir": 20.0, "image": 1, "plant": 1, "unseen": "n"},
                {"box": (0.0, 0.0, 0.4, guess + 0.005), "off_nadir": 26.0, "image": 2, "plant": 1, "unseen": "n"},
                {
                    "box": (0.001, 0.0, 0.401, north_seen_by_b),
                    "off_nadir": 28.0,
                    "image": 3,
                    "plant": 1,
                    "submodel": "submodel_0001",
                    "across": across,
                },
                {
                    "box": (0.001, 0.0, 0.401, north_seen_by_b + 0.005),
                    "off_nadir": 31.0,
                    "image": 4,
                    "plant": 1,
                    "submodel": "submodel_0001",
                    "across": across,
                },
            ]
        )
        plants = merge_views(views)
        assert len(plants) == 1
        return plants.iloc[0]

    p = plant(north_seen_by_b=0.27, guess=0.105)  # seen 17 cm out: beyond both guesses
    assert p["ymax"] == pytest.approx(0.105) and p[["xmin", "ymin", "xmax"]].tolist() == list(truth[:3])
    p = plant(north_seen_by_b=0.27, guess=0.105, across="")  # seen from the north (a leaf tip): trusted
    assert p["ymax"] == pytest.approx(0.2725)
    p = plant(north_seen_by_b=0.10, guess=0.16)  # guesses overshoot (a lopsided plant): the seen side wins
    assert p["ymax"] == pytest.approx(0.1025)
    # beyond the guesses by less than what poses, DSM and submodel alignment disagree by: the seen side wins
    p = plant(north_seen_by_b=0.1 + 0.4 * MERGE_TOLERANCE, guess=0.1)
    assert p["ymax"] == pytest.approx(0.1 + 0.4 * MERGE_TOLERANCE + 0.0025)


def test_two_boxes_of_one_photo_are_two_plants():
    """Plant 2 (64 x 15 cm) stands south of plant 1 (57 x 12 cm); seen from the south, its south side is a guess
    mirrored about the taller plant 1's top, 40 cm too far, so its view contains plant 1's view of the same photo.
    The detector's non-maximum suppression left one box per plant in each photo: two boxes of one photo join only
    by their IoU, never by lying inside one another. The same two boxes from two photos still join (an oblique
    view with a guessed side contains its plant's near-nadir view)."""
    rows = [
        {"box": (0.006, 0.018, 0.644, 0.137), "off_nadir": 31.59, "image": 7, "plant": 1, "unseen": "se"},
        {"box": (-0.005, -0.197, 0.678, 0.351), "off_nadir": 31.61, "image": 7, "plant": 2, "unseen": "se"},
    ]
    plants = merge_views(_views(rows))
    assert sorted(plants["truth_plant_id"]) == [1, 2]
    assert plants.set_index("truth_plant_id").loc[1, "ymin"] == pytest.approx(0.018)
    rows[1]["image"] = 8
    assert len(merge_views(_views(rows))) == 1
