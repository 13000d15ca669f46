"""``mowerhw map ...``: check, show, plot, add and remove keep-out zones (with backups)."""

import json

import numpy as np
import pytest

from mowerhw import map as lawnmap
from mowerhw.cli import main
from mowerhw.cli.map_cmd import parse_polygon


def test_check_and_show(map_file, capsys):
    assert main(["map", "check", str(map_file)]) == 0
    out = capsys.readouterr().out
    assert "ok (version 2; 6 landmarks, 1 mowing and 0 navigation area(s)" in out
    assert main(["map", "show", str(map_file), "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["landmarks"] == 6 and s["area_m2"] == pytest.approx(np.pi * 24, rel=0.01)


def test_check_refuses_a_tampered_map_with_78(map_file, capsys):
    doc = json.loads(map_file.read_text())
    doc["landmarks"][0]["xyz"][0] += 1.0
    map_file.write_text(json.dumps(doc))
    with pytest.raises(SystemExit) as info:
        main(["map", "check", str(map_file)])
    assert info.value.code == 78
    assert "checksum mismatch" in capsys.readouterr().err


def test_add_and_remove_keepout_keep_backups(map_file, capsys):
    before = map_file.read_bytes()
    rc = main(
        ["map", "add-keepout", str(map_file), "--polygon", "0,0 1,0 1,1 0,1", "--name", "flowerbed"]
    )
    assert rc == 0
    msg = capsys.readouterr().out
    assert "added keep-out 'flowerbed'" in msg
    backups = sorted(map_file.parent.glob("lawn.json.*.bak"))
    assert len(backups) == 1 and backups[0].read_bytes() == before
    m = lawnmap.load(map_file)
    assert [z.name for z in m.keepouts] == ["flowerbed"]
    assert main(["map", "remove-keepout", str(map_file), "--name", "flowerbed"]) == 0
    assert lawnmap.load(map_file).keepouts == []
    assert len(list(map_file.parent.glob("lawn.json.*.bak"))) == 2


def test_bad_keepouts_are_refused_and_nothing_is_written(map_file, capsys):
    before = map_file.read_bytes()
    assert main(["map", "add-keepout", str(map_file), "--polygon", "0,0 1,0"]) == 2
    assert "at least 3 corners" in capsys.readouterr().err
    assert main(["map", "add-keepout", str(map_file), "--polygon", "0,0 1,x 1,1"]) == 2
    assert main(["map", "add-keepout", str(map_file), "--polygon", "1,1 3,3 3,1 1,3"]) == 78
    assert "not a simple polygon" in capsys.readouterr().err
    assert main(["map", "remove-keepout", str(map_file), "--name", "nope"]) == 78
    assert map_file.read_bytes() == before
    assert list(map_file.parent.glob("*.bak")) == []


def test_plot_writes_a_png(map_file, tmp_path):
    out = tmp_path / "m.png"
    assert main(["map", "plot", str(map_file), "-o", str(out)]) == 0
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_parse_polygon():
    assert parse_polygon("0,0 1,0;1,1").shape == (3, 2)
    with pytest.raises(ValueError, match="corner 2"):
        parse_polygon("0,0 1 1,1")


def _resigned(path, edit):
    doc = json.loads(path.read_text())
    edit(doc)
    doc.pop("checksum")
    doc["checksum"] = "sha256:" + lawnmap._digest(doc)
    path.write_text(json.dumps(doc))


def test_an_unfit_map_is_shown_and_drawn_with_its_problems(map_file, tmp_path, capsys):
    """A duplicate keep-out and a dock far off: `map check` refuses (78); `show` and
    `plot` still show the map, with the problems marked, and exit 78."""
    zone = {"name": "bed", "polygon": [[0, 0], [1, 0], [1, 1], [0, 1]]}
    twin = {"name": "bed2", "polygon": [[1, 1], [0, 1], [0, 0], [1, 0]]}  # same, other order

    def edit(doc):
        doc["keepout_zones"] = [zone, twin]
        doc["dock"]["position"] = [18.0, 0.0, 0.0]

    _resigned(map_file, edit)
    with pytest.raises(SystemExit) as info:
        main(["map", "check", str(map_file)])
    assert info.value.code == 78
    err = capsys.readouterr().err
    assert "keep-out 'bed2': the same zone as keep-out 'bed'" in err
    assert "dock: 12.0 m outside the lawn (at most 2.0 m" in err
    assert main(["map", "show", str(map_file)]) == 78
    out = capsys.readouterr()
    assert "PROBLEM      keep-out 'bed2': the same zone as keep-out 'bed'" in out.out
    assert "unfit for mowing (2 problem(s)" in out.err
    png = tmp_path / "unfit.png"
    assert main(["map", "plot", str(map_file), "-o", str(png)]) == 78
    assert png.stat().st_size > 1000


def test_show_gives_the_map_frames_error_or_says_there_is_none(map_file, capsys):
    """`map show` says how far the map's frame may be off the ground (1σ), when the teach
    measured it, and says so when it did not (a map taught before)."""
    assert main(["map", "show", str(map_file)]) == 0
    assert "frame        not measured" in capsys.readouterr().out
    m = lawnmap.load(map_file)
    m.frame_covariance = np.diag([4e-6, 1e-6, np.radians(0.01) ** 2, 1e-6])
    m.save(map_file)
    assert main(["map", "show", str(map_file), "--json"]) == 0
    f = json.loads(capsys.readouterr().out)["frame_sigma"]
    assert f == {"shift_x_m": 0.002, "shift_y_m": 0.001, "turn_deg": 0.01, "scale_percent": 0.1}
    assert main(["map", "show", str(map_file)]) == 0
    assert "shift 0.002 / 0.001 m, turn 0.01°, scale 0.1 %" in capsys.readouterr().out
