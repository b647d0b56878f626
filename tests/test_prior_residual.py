"""benchmarks.prior_residual: the motion prior's residual pose error, on a real tiny scene."""

from __future__ import annotations

import json

from benchmarks import prior_residual as pr
from fastenerf.data.formats import load_scene_folder


def test_longer_windows_leave_less_error_and_too_long_is_none(tiny_scene):
    scene = load_scene_folder(tiny_scene)
    r = pr.residuals(scene, 2.0, [5, 21, 999], order=1)
    assert abs(r["given"] - 2.0) < 0.05  # the study turns every pose by 2°
    assert r[21] < r[5] < 0.5 * r["given"]
    assert r[999] is None


def test_table_json_and_bad_input(tiny_scene, tmp_path, capsys):
    out = tmp_path / "pr.json"
    argv = [str(tiny_scene), "--levels", "1", "--windows", "5", "9", "--json", str(out)]
    assert pr.main(argv) == 0
    table = capsys.readouterr().out
    assert "| window 5 | window 9 |" in table and "| 1° |" in table
    got = json.loads(out.read_text())["residual_deg"][f"{tiny_scene} 1.0"]
    assert set(got) == {"given", "5", "9"} and got["9"] < got["5"] < got["given"]
    for bad in (["--windows", "4"], ["--levels", "-1"], ["--levels", "nan"]):
        assert pr.main([str(tiny_scene), *bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("prior_residual: error:")
    assert pr.main([str(tmp_path / "missing")]) == 2


def test_json_never_replaces_another_file_or_a_folder(tiny_scene, tmp_path, capsys):
    """--json is checked before any work: a folder or a JSON that is not this benchmark's
    (a scene.json) is refused with one line and exit 2 and left as it was; its own is replaced."""
    other = tmp_path / "scene.json"
    other.write_text((tiny_scene / "scene.json").read_text())
    before = other.read_bytes()
    for target in (other, tmp_path):
        argv = [str(tiny_scene), "--levels", "1", "--windows", "5", "--json", str(target)]
        assert pr.main(argv) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--json" in err[0]
    assert other.read_bytes() == before
    own = tmp_path / "pr.json"
    for _ in range(2):  # written, then replaced
        assert (
            pr.main([str(tiny_scene), "--levels", "1", "--windows", "5", "--json", str(own)]) == 0
        )
    assert "residual_deg" in json.loads(own.read_text())
