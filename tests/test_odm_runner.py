"""Module 2 (odm_runner): docker command, Docker runner, NodeODM client, output checking, folder files."""

from __future__ import annotations

import email.parser
import io
import json
import os
import re
import shutil
import subprocess
import sys
import threading
import uuid as uuidlib
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

import pytest

from matchplant.core.runtime.config import load_config
from matchplant.core.runtime.errors import ConfigError, DependencyError, InputError
from matchplant.odm_runner.config import ODMRunError, OdmRunnerConfig
from matchplant.odm_runner.docker import CONTAINER_PROJECT, check_docker, docker_command
from matchplant.odm_runner.inputs import find_gcp_file, odm_arguments
from matchplant.odm_runner.nodeodm import NODEODM_OUTPUTS
from matchplant.odm_runner.outputs import check_outputs
from matchplant.odm_runner.run import run

ROOT = Path(__file__).resolve().parents[1]
FOLDER = ROOT / "2_odm_runner"


def make_project(tmp_path: Path, name: str = "field 1", n_images: int = 3, gcp: bool = False) -> Path:
    project = tmp_path / name
    (project / "images").mkdir(parents=True)
    for i in range(n_images):
        (project / "images" / f"IMG_{i:04d}.JPG").write_bytes(b"\xff\xd8fake jpeg\xff\xd9")
    if gcp:
        (project / "images" / "gcp_list.txt").write_text("EPSG:32615\n1 2 3 10 20 IMG_0000.JPG g1\n")
    return project


def out_of(project: Path) -> Path:
    """Where these tests keep module 2's own files unless a test names the folder (the default, runs/odm_runner,
    is relative to the working folder)."""
    return project.parent / "odm_runner_out"


def cfg_for(project: Path, *overrides: str) -> OdmRunnerConfig:
    out = [] if any(o.startswith("output_dir=") for o in overrides) else [f"output_dir={out_of(project)}"]
    return load_config(OdmRunnerConfig, None, [f"project_dir={project}", *out, *overrides])


# --------------------------------------------------------------------------------------------------
# the docker command (pure function)


def test_docker_command_defaults_linux(tmp_path):
    project = make_project(tmp_path)
    argv = docker_command(cfg_for(project), platform="linux", uid=1000, gid=1001)
    assert argv[:4] == ["docker", "run", "--rm", "-i"]
    assert "-t" not in argv and "-ti" not in argv and "-it" not in argv  # no TTY: runs from cron/GUI/CI
    assert argv[argv.index("--user") + 1] == "1000:1001"
    # a path with a space stays one argument: the whole 'host:container' mount spec
    assert argv[argv.index("-v") + 1] == f"{project}:{CONTAINER_PROJECT}"
    image = argv.index("opendronemap/odm")
    odm = argv[image + 1 :]
    assert odm[:2] == ["--project-path", "/datasets"]
    assert "--dsm" in odm and "--dtm" in odm
    assert odm[odm.index("--orthophoto-resolution") + 1] == "0.5"
    assert "--gcp" not in odm
    assert not any("optimize-disk-space" in a for a in argv)  # undistorted images are kept


def test_docker_command_gcp_extra_options_and_gpu(tmp_path):
    project = make_project(tmp_path, gcp=True)
    cfg = cfg_for(
        project,
        "odm.extra={feature-quality: high, fast-orthophoto: true, use-3dmesh: false}",
        "odm.dtm=false",
        "odm.dem_resolution=2",
        "docker.gpus=true",
        "docker.image=opendronemap/odm:gpu",
        "docker.extra_args=[--memory, 16g]",
    )
    gcp = find_gcp_file(cfg)
    assert gcp == project / "images" / "gcp_list.txt"
    argv = docker_command(cfg, platform="darwin", uid=501, gid=20, gcp_file=gcp)
    assert argv[argv.index("--user") + 1] == "501:20"
    assert argv[argv.index("--gpus") + 1] == "all"
    assert argv[argv.index("--memory") + 1] == "16g"
    odm = argv[argv.index("opendronemap/odm:gpu") + 1 :]
    assert odm[odm.index("--gcp") + 1] == f"{CONTAINER_PROJECT}/images/gcp_list.txt"
    assert "--dtm" not in odm and "--dsm" in odm
    assert odm[odm.index("--dem-resolution") + 1] == "2"
    assert odm[odm.index("--feature-quality") + 1] == "high"
    assert "--fast-orthophoto" in odm and "--use-3dmesh" not in odm
    # docker's own arguments come before the image, ODM's after it
    assert argv.index("--memory") < argv.index("opendronemap/odm:gpu")


def test_docker_command_gcp_and_images_outside_project(tmp_path):
    project = make_project(tmp_path)
    elsewhere = tmp_path / "survey data"
    (elsewhere / "pics").mkdir(parents=True)
    gcp = elsewhere / "my gcps.txt"
    gcp.write_text("EPSG:32615\n")
    cfg = cfg_for(project, f"images_dir={elsewhere / 'pics'}", f"gcp_file={gcp}")
    argv = docker_command(cfg, platform="linux", uid=1, gid=1, gcp_file=find_gcp_file(cfg))
    mounts = [argv[i + 1] for i, a in enumerate(argv) if a == "-v"]
    assert f"{elsewhere / 'pics'}:{CONTAINER_PROJECT}/images:ro" in mounts
    assert f"{gcp}:/datasets/gcp/my gcps.txt:ro" in mounts
    assert argv[argv.index("--gcp") + 1] == "/datasets/gcp/my gcps.txt"


def test_docker_command_windows_paths(tmp_path):
    cfg = OdmRunnerConfig(
        project_dir=r"C:\Users\Ana Lima\Field 2024", gcp_file=r"C:\Users\Ana Lima\Field 2024\gcp_list.txt"
    )
    argv = docker_command(cfg, platform="win32", gcp_file=cfg.gcp_file)
    assert "--user" not in argv  # Docker Desktop on Windows maps ownership itself
    assert argv[argv.index("-v") + 1] == r"C:\Users\Ana Lima\Field 2024:/datasets/code"
    assert argv[argv.index("--gcp") + 1] == "/datasets/code/gcp_list.txt"


def test_odm_extra_rejects_options_that_lose_outputs(tmp_path):
    project = make_project(tmp_path)
    with pytest.raises(ConfigError, match="optimize-disk-space"):
        cfg_for(project, "odm.extra={optimize-disk-space: true}")
    assert odm_arguments(cfg_for(project).odm) == ["--dsm", "--dtm", "--orthophoto-resolution", "0.5"]


# --------------------------------------------------------------------------------------------------
# the Docker runner, with a stand-in 'docker' program (no Docker engine on test machines)


FAKE_DOCKER = r"""#!{python}
import sys, time
args = sys.argv[1:]
if args[:1] == ["info"]:
    print("{state}"); sys.exit({info_code})
with open({record!r}, "w") as fh:
    fh.write("\n".join(args))
for i in range(3):
    print(f"[INFO] fake ODM step {{i}}", flush=True)
sys.exit({run_code})
"""


def fake_docker(tmp_path: Path, *, run_code: int = 0, info_code: int = 0) -> tuple[Path, Path]:
    record = tmp_path / "docker_args.txt"
    exe = tmp_path / "bin" / "docker"
    exe.parent.mkdir(exist_ok=True)
    exe.write_text(
        FAKE_DOCKER.format(
            python=sys.executable,
            record=str(record),
            run_code=run_code,
            info_code=info_code,
            state="27.0" if info_code == 0 else "Cannot connect",
        )
    )
    exe.chmod(0o755)
    return exe, record


@pytest.mark.skipif(os.name == "nt", reason="stand-in docker is a POSIX script")
def test_run_docker_streams_log_and_checks_exit_code(tmp_path):
    project = make_project(tmp_path)
    exe, record = fake_docker(tmp_path, run_code=3)
    cfg = cfg_for(project, f"docker.command={exe}", f"output_dir={tmp_path / 'out'}")
    with pytest.raises(ODMRunError, match="exit code 3") as err:
        run(cfg)
    assert "fake ODM step 2" in str(err.value)  # the end of ODM's log is in the message
    log_text = (tmp_path / "out" / "odm_docker.log").read_text()
    assert "fake ODM step 0" in log_text and "fake ODM step 2" in log_text
    args = record.read_text().splitlines()
    assert args[0] == "run" and args[args.index("-v") + 1] == f"{project}:{CONTAINER_PROJECT}"


@pytest.mark.skipif(os.name == "nt", reason="stand-in docker is a POSIX script")
def test_run_docker_success_then_reports_missing_outputs(tmp_path):
    project = make_project(tmp_path)
    exe, _ = fake_docker(tmp_path, run_code=0)
    cfg = cfg_for(project, f"docker.command={exe}", f"output_dir={tmp_path / 'out'}")
    with pytest.raises(InputError) as err:  # the fake ODM wrote nothing: every output is missing
        run(cfg)
    assert "odm_dem/dtm.tif" in str(err.value) and "--dtm" in str(err.value)
    manifest = json.loads((tmp_path / "out" / "odm_manifest.json").read_text())
    assert manifest["run"]["exit_code"] == 0 and manifest["ok"] is False
    assert manifest["outputs"]["dsm"] == {"path": "odm_dem/dsm.tif", "exists": False, "produced_by": "--dsm"}


def test_docker_missing_or_not_running(tmp_path):
    with pytest.raises(DependencyError, match="not found"):
        check_docker(str(tmp_path / "no-such-docker"))
    if os.name != "nt":
        exe, _ = fake_docker(tmp_path, info_code=1)
        with pytest.raises(DependencyError, match="not running"):
            check_docker(str(exe))


# --------------------------------------------------------------------------------------------------
# output checking on the synthetic field, and on copies with pieces removed


def test_check_outputs_synthetic_field(tiny_field, tmp_path):
    report = check_outputs(tiny_field.root)
    assert report.ok, report.problems
    assert report.details["undistorted_shots"] == report.details["undistorted_images"] > 0
    cfg = cfg_for(tiny_field.root, "check_only=true", f"output_dir={tmp_path}")
    run(cfg)
    manifest = json.loads((tmp_path / "odm_manifest.json").read_text())
    assert manifest["ok"] and manifest["run"] is None
    assert all(manifest["outputs"][k]["exists"] for k in ("dsm", "dtm", "orthophoto", "undistorted_images"))


def test_default_run_writes_nothing_into_the_odm_project(tiny_field, tmp_path, monkeypatch):
    """Issue 29: module 2's manifest and logs go to runs/odm_runner like every module's outputs, and the ODM
    project keeps exactly ODM's files."""
    project = tmp_path / "project"
    copy_outputs(tiny_field.root, project)
    before = sorted(p.relative_to(project) for p in project.rglob("*"))
    monkeypatch.chdir(tmp_path)
    run(load_config(OdmRunnerConfig, None, [f"project_dir={project}", "check_only=true"]))
    assert sorted(p.relative_to(project) for p in project.rglob("*")) == before
    manifest = json.loads((tmp_path / "runs" / "odm_runner" / "odm_manifest.json").read_text())
    assert manifest["ok"]


def copy_outputs(src: Path, dst: Path) -> None:
    """Copy the ODM outputs of a project (not its raw images or truth, at the top level only)."""
    top = {"images", "images_nogps", "truth"}
    shutil.copytree(src, dst, ignore=lambda d, names: [n for n in names if Path(d) == src and n in top])


@pytest.mark.parametrize(
    "remove, option",
    [
        ("odm_dem/dtm.tif", "--dtm"),
        ("odm_dem/dsm.tif", "--dsm"),
        ("opensfm/undistorted", "--optimize-disk-space"),
        ("odm_orthophoto/odm_orthophoto.tif", "--skip-orthophoto"),
        ("odm_georeferencing/coords.txt", "gcp_list.txt"),
    ],
)
def test_check_outputs_names_the_option_for_each_missing_piece(tiny_field, tmp_path, remove, option):
    copy = tmp_path / "project"
    copy_outputs(tiny_field.root, copy)
    target = copy / remove
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    report = check_outputs(copy)
    assert not report.ok
    assert any(remove.split("/")[-1] in p and option in p for p in report.problems), report.problems


@pytest.mark.parametrize(
    "damage, message",
    [
        (lambda p: p.write_bytes(p.read_bytes()[:1000]), "truncated"),
        (lambda p: p.write_text(json.dumps([dict(json.loads(p.read_text())[0], shots={})])), "no images"),
    ],
)
def test_check_outputs_reads_the_reconstruction(tiny_field, tmp_path, damage, message):
    copy = tmp_path / "project"
    copy_outputs(tiny_field.root, copy)
    damage(copy / "opensfm" / "reconstruction.json")
    report = check_outputs(copy)
    assert any(p.startswith("opensfm/reconstruction.json") and message in p for p in report.problems), report.problems
    with pytest.raises(InputError, match="reconstruction.json"):  # check_only: no manifest of a failed check
        run(cfg_for(copy, "check_only=true", f"output_dir={tmp_path / 'out'}"))
    assert not (tmp_path / "out" / "odm_manifest.json").exists()


def test_check_outputs_undistorted_image_missing(tiny_field, tmp_path):
    copy = tmp_path / "project"
    copy_outputs(tiny_field.root, copy)
    first = sorted((copy / "opensfm/undistorted/images").iterdir())[0]
    first.unlink()
    report = check_outputs(copy)
    assert any("have no undistorted image" in p and first.name in p for p in report.problems)


# --------------------------------------------------------------------------------------------------
# NodeODM: a small local HTTP server that stands in for NodeODM (127.0.0.1 only), answering the documented
# task API (https://github.com/OpenDroneMap/NodeODM/blob/master/docs/index.adoc): /info, /task/new/init,
# /task/new/upload/<uuid>, /task/new/commit/<uuid>, /task/<uuid>/info, /task/<uuid>/download/all.zip.
# It is NOT NodeODM: it runs no photogrammetry; "processing" advances the progress on each info call and
# the result zip holds a prepared ODM project's outputs, filtered by the 'outputs' the client asked for.


class FakeNodeODM:
    def __init__(self, results: Path, steps: int = 3):
        self.results = results
        self.steps = steps
        self.tasks: dict[str, dict] = {}
        self.calls: list[str] = []
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *a):  # keep test output clean
                pass

            def _json(self, data, code=200):
                body = json.dumps(data).encode()
                self.send_response(code)
                self.send_header("Content-Type", "application/json")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def _form(self) -> dict:
                length = int(self.headers.get("Content-Length", 0))
                raw = self.rfile.read(length)
                if "multipart/form-data" not in self.headers.get("Content-Type", ""):
                    return {}  # commit has no body
                msg = email.parser.BytesParser().parsebytes(
                    b"Content-Type: " + self.headers["Content-Type"].encode() + b"\r\n\r\n" + raw
                )
                fields = {}
                for part in msg.get_payload():
                    name = part.get_param("name", header="content-disposition")
                    fields.setdefault(name, []).append((part.get_filename(), part.get_payload(decode=True)))
                return fields

            def do_GET(self):
                path = self.path.split("?")[0]
                outer.calls.append("GET " + path)
                if path == "/info":
                    return self._json(
                        {
                            "version": "2.2.1",
                            "taskQueueCount": len(outer.tasks),
                            "engine": "odm",
                            "engineVersion": "3.5.0",
                            "maxImages": None,
                        }
                    )
                m = re.fullmatch(r"/task/([^/]+)/(info|download/all\.zip|output)", path)
                if not m or m.group(1) not in outer.tasks:
                    return self._json({"error": "Invalid uuid"})
                task = outer.tasks[m.group(1)]
                if m.group(2) == "info":
                    if task["status"] == 20:
                        task["progress"] = min(100, task["progress"] + 100 // outer.steps + 1)
                        if task["progress"] >= 100:
                            task["status"] = 40
                    return self._json(
                        {
                            "uuid": m.group(1),
                            "name": task["name"],
                            "dateCreated": 1_700_000_000_000,
                            "processingTime": 1000,
                            "status": {"code": task["status"]},
                            "options": task["options"],
                            "imagesCount": len(task["files"]),
                            "progress": task["progress"],
                        }
                    )
                if m.group(2) == "output":
                    return self._json(["fake log line"])
                body = outer.zip_bytes(task["outputs"])
                self.send_response(200)
                self.send_header("Content-Type", "application/zip")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def do_POST(self):
                path = self.path.split("?")[0]
                outer.calls.append("POST " + path)
                form = self._form()
                if path == "/task/new/init":
                    uid = str(uuidlib.uuid4())
                    opts = json.loads(form["options"][0][1])
                    outs = json.loads(form["outputs"][0][1]) if "outputs" in form else []
                    outer.tasks[uid] = {
                        "name": form["name"][0][1].decode(),
                        "options": opts,
                        "outputs": outs,
                        "files": [],
                        "status": 10,
                        "progress": 0,
                    }
                    return self._json({"uuid": uid})
                m = re.fullmatch(r"/task/new/(upload|commit)/([^/]+)", path)
                if not m or m.group(2) not in outer.tasks:
                    return self._json({"error": "Invalid uuid"})
                task = outer.tasks[m.group(2)]
                if m.group(1) == "upload":
                    task["files"] += [name for name, _ in form.get("images", [])]
                    return self._json({"success": True})
                task["status"] = 20
                return self._json({"uuid": m.group(2)})

        self.server = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.port = self.server.server_address[1]
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)

    def zip_bytes(self, outputs: list[str]) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            for p in sorted(self.results.rglob("*")):
                rel = p.relative_to(self.results).as_posix()
                if p.is_file() and any(rel == o or rel.startswith(o.rstrip("/") + "/") for o in outputs):
                    zf.write(p, rel)
        return buf.getvalue()

    def __enter__(self):
        self.thread.start()
        return self

    def __exit__(self, *exc):
        self.server.shutdown()
        self.server.server_close()


def nodeodm_cfg(project: Path, port: int, *extra: str) -> OdmRunnerConfig:
    return cfg_for(
        project,
        "backend=nodeodm",
        f"nodeodm.url=http://127.0.0.1:{port}",
        "nodeodm.poll_seconds=0.05",
        "nodeodm.parallel_uploads=2",
        *extra,
    )


def test_nodeodm_upload_process_download(tiny_field, tmp_path):
    project = make_project(tmp_path, gcp=True)
    with FakeNodeODM(tiny_field.root) as node:
        report = run(nodeodm_cfg(project, node.port))
        assert report.ok, report.problems
        (task,) = node.tasks.values()
        assert sorted(task["files"]) == ["IMG_0000.JPG", "IMG_0001.JPG", "IMG_0002.JPG", "gcp_list.txt"]
        assert task["options"] == [
            {"name": "dsm", "value": True},
            {"name": "dtm", "value": True},
            {"name": "orthophoto-resolution", "value": 0.5},
        ]
        assert task["outputs"] == NODEODM_OUTPUTS
    # the downloaded outputs are byte-identical to the server's
    for rel in ("odm_dem/dsm.tif", "opensfm/undistorted/reconstruction.json", "odm_georeferencing/coords.txt"):
        assert (project / rel).read_bytes() == (tiny_field.root / rel).read_bytes()
    state = json.loads((out_of(project) / "nodeodm_task.json").read_text())
    assert state["uuid"] in node.tasks
    manifest = json.loads((out_of(project) / "odm_manifest.json").read_text())
    assert manifest["ok"] and manifest["run"]["task"] == state["uuid"]
    assert not (project / ".nodeodm_download").exists()


def test_nodeodm_resumes_saved_task_without_uploading(tiny_field, tmp_path):
    project = make_project(tmp_path)
    with FakeNodeODM(tiny_field.root) as node:
        uid = "0f0e0d0c-0000-4000-8000-000000000001"
        node.tasks[uid] = {
            "name": "earlier",
            "options": [],
            "outputs": NODEODM_OUTPUTS,
            "files": ["a.JPG"],
            "status": 20,
            "progress": 40,
        }
        out_of(project).mkdir()
        (out_of(project) / "nodeodm_task.json").write_text(json.dumps({"uuid": uid}))
        run(nodeodm_cfg(project, node.port))
        assert not any("/task/new" in c for c in node.calls)
        assert f"GET /task/{uid}/download/all.zip" in node.calls
    assert (project / "odm_dem" / "dsm.tif").is_file()


def test_nodeodm_unreachable_is_a_clear_error(tmp_path):
    project = make_project(tmp_path)
    with ThreadingHTTPServer(("127.0.0.1", 0), BaseHTTPRequestHandler) as s:
        port = s.server_address[1]  # a port that is free again once closed
    with pytest.raises(DependencyError, match="cannot reach the NodeODM server"):
        run(nodeodm_cfg(project, port, "nodeodm.timeout=2"))


# --------------------------------------------------------------------------------------------------
# the numbered folder


@pytest.mark.slow
def test_folder_config_loads_and_help_works():
    cfg = load_config(OdmRunnerConfig, FOLDER / "config.yaml", check_paths=False)
    assert cfg.odm.dsm and cfg.odm.dtm and cfg.odm.orthophoto_resolution == 0.5 and cfg.backend == "docker"
    text = (FOLDER / "config.yaml").read_text()
    keys = [ln for ln in text.splitlines() if re.match(r"^\s*[a-z_]+:", ln)]
    comments = [ln for ln in text.splitlines() if ln.strip().startswith("#")]
    assert len(comments) >= len(keys)  # every key commented
    res = subprocess.run([sys.executable, str(FOLDER / "odm_runner.py"), "--help"], capture_output=True, text=True)
    assert res.returncode == 0 and "--project" in res.stdout
    if shutil.which("bash"):
        res = subprocess.run(
            ["bash", str(FOLDER / "run_odm.sh"), "--help"],
            capture_output=True,
            text=True,
            env=dict(os.environ, PYTHON=sys.executable),
        )
        assert res.returncode == 0 and "--backend" in res.stdout


def test_cli_error_without_traceback(tmp_path):
    res = subprocess.run(
        [sys.executable, str(FOLDER / "odm_runner.py"), "--set", f"project_dir={tmp_path / 'nope'}"],
        capture_output=True,
        text=True,
    )
    assert res.returncode == 2 and "Traceback" not in res.stderr and "project_dir" in res.stderr
