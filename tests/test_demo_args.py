"""The demo's options are checked before any work (issue 39): a wrong choice, a negative number or a ``--from``
that the output folder cannot continue ends with the problem and its fix (exit 2), and nothing is written."""

from __future__ import annotations

import pytest

from matchplant.demo import main


@pytest.mark.parametrize(
    ("args", "words"),
    [
        (["--from", "9_stats"], ["have not finished", "without --from first"]),
        (["--from", "9_stat"], ["did you mean '9_stats'", "one of: 0_gps"]),
        (["--minutes", "-5"], ["--minutes -5", "0 or more"]),
        (["--epochs", "0"], ["--epochs 0", "1 or more"]),
        (["--noise", "realistc"], ["did you mean 'realistic'", "one of: exact, realistic"]),
        (["--preset", "huge"], ["'huge'", "one of: tiny, small, large"]),
        (["--epochs", "two"], ["invalid int value", "--help"]),
    ],
)
def test_a_wrong_option_is_refused_before_any_work(tmp_path, capsys, args, words):
    out = tmp_path / "demo"
    with pytest.raises(SystemExit) if "two" in args else _no_raise():
        rc = main(["--out", str(out), *args])
        assert rc == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "\n  fix:  " in err, err
    for word in words:
        assert word in err, err
    assert not out.exists()  # no field generated, no step run


def test_from_a_step_of_a_finished_demo_is_accepted(tmp_path):
    """--from passes the check once the steps before it have their stamps (the check itself, not a run)."""
    from argparse import Namespace

    from matchplant.demo import check_args, pipeline_spec

    names = [s["name"] for s in pipeline_spec(tmp_path, "", epochs=1, minutes=0, pretrained="none", tile=128)["steps"]]
    (tmp_path / ".pipeline").mkdir()
    for n in names[: names.index("9_stats")]:
        (tmp_path / ".pipeline" / f"{n}.json").write_text("{}")
    args = Namespace(preset="tiny", noise="exact", pretrained="none", epochs=1, minutes=0.0, threads=0)
    check_args(Namespace(**vars(args), out=tmp_path, from_step="9_stats"))


class _no_raise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
