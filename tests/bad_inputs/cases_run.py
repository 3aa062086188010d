"""The pipeline runner (``matchplant run pipeline.yaml``): every step is checked before any runs, so each broken
pipeline below must fail with exit 2 and leave no output of its first step behind (the harness checks that the
output folder holds nothing new but the log). Two pipelines must work: Windows BOM + CRLF with non-ASCII paths,
and a chain through ``${step.key}`` whose input does not exist until the earlier step has run."""

from __future__ import annotations

import json
from pathlib import Path

from harness import Case, Work


def crs(w: Work) -> str:
    return json.loads((w.artifacts / "field" / "truth" / "field.json").read_text())["crs"]


def gps_step(w: Work, name: str = "gps", **extra: str) -> str:
    images = w.copy("field/images_nogps") if not (w.inputs / "images_nogps").exists() else w.inputs / "images_nogps"
    log = w.copy("field/gnss/events.txt") if not (w.inputs / "events.txt").exists() else w.inputs / "events.txt"
    config = {"images": str(images), "gnss_log": str(log), "log_crs": crs(w), **extra}
    return f"  - name: {name}\n    module: gps_embeder\n    config: {json.dumps(config)}\n"


def gcp_step(w: Work, name: str = "gcp", images: str = "${gps.output_dir}/images", **extra: str) -> str:
    survey = (
        w.copy("field/gcp/gcp_survey.csv")
        if not (w.inputs / "gcp_survey.csv").exists()
        else w.inputs / "gcp_survey.csv"
    )
    config = {"images": images, "survey": str(survey), "survey_crs": crs(w), "auto": True, **extra}
    return f"  - name: {name}\n    module: gcp_finder\n    config: {json.dumps(config)}\n"


def tiles_step(w: Work, name: str = "tiles", **extra) -> str:
    images = (
        w.copy("field/opensfm/undistorted/images", "undistorted")
        if not (w.inputs / "undistorted").exists()
        else w.inputs / "undistorted"
    )
    boxes = w.copy("field/truth/boxes_undistorted.json")
    config = {"images": str(images), "annotations": str(boxes), "tile_size": 128, "overlap": 32, "workers": 1, **extra}
    return f"  - name: {name}\n    module: img_splitter\n    config: {json.dumps(config)}\n"


def pipeline(w: Work, steps: str, head: str = "", name: str = "pipeline.yaml") -> list[str]:
    path = w.inputs / name
    path.write_text(f"output_dir: {json.dumps(str(w.out))}\n{head}steps:\n{steps}", encoding="utf-8")
    return [str(path)]


# -- a problem in a later step is found before the first step runs -------------------------------------------------


def unknown_module(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + "  - name: tiles\n    module: img_spliter\n")


def unknown_key_in_step_3(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w) + tiles_step(w, tile_sise=256))


def ref_unknown_step(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, images="${gsp.output_dir}/images"))


def ref_unknown_key(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, images="${gps.output_folder}/images"))


def ref_unknown_top_level(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, survey_crs="${crs}"), head="cr: EPSG:32614\n")


def ref_forward(w: Work) -> list[str]:
    return pipeline(w, gcp_step(w) + gps_step(w))


def ref_cycle(w: Work) -> list[str]:
    return pipeline(w, gps_step(w, output_dir="${gcp.output_dir}/gps") + gcp_step(w))


def ref_malformed(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, images="${gps.output_dir/images"))


def duplicate_names(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, name="gps"))


def wrong_type(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w) + tiles_step(w, tile_size="big"))


def out_of_range(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w) + tiles_step(w, tile_size=-5))


def missing_steps(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w), name="pipeline.yaml") and _rewrite(
        w, lambda t: t.replace("steps:\n", "step:\n")
    )


def _rewrite(w: Work, change) -> list[str]:
    path = w.inputs / "pipeline.yaml"
    path.write_text(change(path.read_text(encoding="utf-8")), encoding="utf-8")
    return [str(path)]


def empty_file(w: Work) -> list[str]:
    (w.inputs / "pipeline.yaml").write_text("\n# nothing yet\n")
    return [str(w.inputs / "pipeline.yaml")]


def yaml_syntax_error(w: Work) -> list[str]:
    pipeline(w, gps_step(w) + gcp_step(w))
    return _rewrite(w, lambda t: t.replace('"auto": true}', '"auto": true'))


def tab_indented(w: Work) -> list[str]:
    pipeline(w, gps_step(w) + gcp_step(w))
    return _rewrite(w, lambda t: t.replace("  - name: gcp", "\t- name: gcp"))


def step_is_text(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + "  - gcp_finder\n")


def step_key_typo(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w).replace("    config:", "    confg:"))


def missing_input_of_step_2(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, survey=str(w.inputs / "gcp_survey_2024.csv")))


def literal_path_to_earlier_output(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, images=str(w.out / "gps" / "images")))


def required_key_missing(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w).replace(', "survey": ', ', "survey_old": '))


def output_is_an_input(w: Work) -> list[str]:
    gps = gps_step(w)
    return pipeline(w, gps + gcp_step(w, output_dir=str(w.inputs / "images_nogps")))


def output_contains_pipeline_inputs(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w, output_dir=str(w.inputs)))


def config_file_missing(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + gcp_step(w)[:-1] + "\n    config_file: gcp.yaml\n")


def pipeline_step_in_pipeline(w: Work) -> list[str]:
    return pipeline(w, gps_step(w) + "  - name: inner\n    module: run\n    config: {pipeline: other.yaml}\n")


def several_problems(w: Work) -> list[str]:
    return pipeline(
        w, gps_step(w, gnss_logg="events.txt") + gcp_step(w, survey_crs="${crs}") + tiles_step(w, overlap=999)
    )


def from_unknown_step(w: Work) -> list[str]:
    return [*pipeline(w, gps_step(w) + gcp_step(w)), "--from", "GCP"]


# -- pipelines that must work ----------------------------------------------------------------------------------------


def bom_crlf_unicode(w: Work) -> list[str]:
    folder = w.inputs / "saison été 2024"
    folder.mkdir()
    args = pipeline(w, gps_step(w) + gcp_step(w), head="crs: EPSG:32614\n")
    text = Path(args[0]).read_text(encoding="utf-8")
    path = folder / "chaîne de traitement.yaml"
    path.write_bytes(b"\xef\xbb\xbf" + text.replace("\n", "\r\n").encode("utf-8"))
    Path(args[0]).unlink()
    return [str(path)]


def chained_outputs_written(w: Work) -> None:
    assert len(list((w.out / "gps" / "images").glob("*.JPG"))) == 9
    assert (w.out / "gcp" / "gcp_list.txt").is_file()
    assert {p.stem for p in (w.out / ".pipeline").glob("*.json")} == {"gps", "gcp"}


CASES = [
    Case(
        "run-unknown-module",
        "run",
        unknown_module,
        mentions=("img_spliter", "did you mean 'img_splitter'", "pipeline.yaml"),
    ),
    Case(
        "run-unknown-key-in-step-3",
        "run",
        unknown_key_in_step_3,
        mentions=("tile_sise", "did you mean 'tile_size'", "step 3 'tiles'"),
    ),
    Case(
        "run-ref-unknown-step", "run", ref_unknown_step, mentions=("${gsp.output_dir}", "did you mean 'gps.output_dir'")
    ),
    Case("run-ref-unknown-key", "run", ref_unknown_key, mentions=("output_folder", "did you mean 'output_dir'")),
    Case("run-ref-unknown-top-level-key", "run", ref_unknown_top_level, mentions=("${crs}", "did you mean 'cr'")),
    Case("run-ref-forward", "run", ref_forward, mentions=("step 'gps', which runs later", "move 'gps' before 'gcp'")),
    Case("run-ref-cycle", "run", ref_cycle, mentions=("a cycle",)),
    Case("run-ref-malformed", "run", ref_malformed, mentions=("malformed reference", "images")),
    Case("run-duplicate-step-names", "run", duplicate_names, mentions=("two steps are named 'gps'",)),
    Case("run-wrong-type", "run", wrong_type, mentions=("tile_size", "whole number")),
    Case("run-out-of-range", "run", out_of_range, mentions=("tile_size", "minimum")),
    Case("run-missing-steps", "run", missing_steps, mentions=("'steps'", "did you mean 'steps'")),
    Case("run-empty-file", "run", empty_file, mentions=("pipeline.yaml", "empty")),
    Case("run-yaml-syntax-error", "run", yaml_syntax_error, mentions=("pipeline.yaml", "line")),
    Case("run-tab-indentation", "run", tab_indented, mentions=("line 6", "tab")),
    Case("run-step-is-text", "run", step_is_text, mentions=("- module: gcp_finder",)),
    Case("run-step-key-typo", "run", step_key_typo, mentions=("confg", "did you mean 'config'")),
    Case("run-missing-input-of-step-2", "run", missing_input_of_step_2, mentions=("gcp_survey_2024.csv", "survey")),
    Case(
        "run-literal-path-to-earlier-output",
        "run",
        literal_path_to_earlier_output,
        mentions=("${gps.output_dir}/images",),
    ),
    Case("run-required-key-missing", "run", required_key_missing, mentions=("survey_old", "did you mean 'survey'")),
    Case("run-output-is-an-input", "run", output_is_an_input, mentions=("output_dir", "images")),
    Case("run-output-contains-inputs", "run", output_contains_pipeline_inputs, mentions=("output_dir", "contains")),
    Case("run-config-file-missing", "run", config_file_missing, mentions=("gcp.yaml",)),
    Case("run-pipeline-in-pipeline", "run", pipeline_step_in_pipeline, mentions=("cannot run a pipeline",)),
    Case(
        "run-several-problems-at-once",
        "run",
        several_problems,
        mentions=("3 problems", "step 1 'gps'", "step 2 'gcp'", "step 3 'tiles'", "overlap"),
    ),
    Case("run-from-unknown-step", "run", from_unknown_step, mentions=("GCP", "did you mean 'gcp'")),
    Case("run-bom-crlf-unicode-paths", "run", bom_crlf_unicode, expect="ok", check=chained_outputs_written),
]
