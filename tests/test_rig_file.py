"""Rig files (formats.md section 1): round trip, strict errors, and `lightflow rig check`."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from lightflow.app.cli import main as cli_main
from lightflow.app.core.errors import ConfigError
from lightflow.app.core.rig import load_rig, save_rig

RIGS = Path(__file__).resolve().parents[1] / "app" / "rigs"
TWO = json.loads((RIGS / "two-projector.json").read_text())
ONE = json.loads((RIGS / "single-projector.json").read_text())


def write(tmp_path: Path, data, name="rig.json") -> Path:
    path = tmp_path / name
    path.write_text(json.dumps(data))
    return path


def edited(base, edit):
    d = copy.deepcopy(base)
    edit(d)
    return d


def proj0(d):
    return d["projectors"][0]


def pat0(d):
    return d["projectors"][0]["patterns"][0]


def parallel_rig():
    """Two projectors side by side, same orientation and depth: h(z) is constant."""

    def edit(d):
        for p, x in zip(d["projectors"], (0.2, -0.2), strict=True):
            p["R"] = np.eye(3).tolist()
            p["t"] = [x, 0.0, 0.0]

    return edited(TWO, edit)


@pytest.mark.parametrize("name", ["two-projector", "single-projector"])
def test_round_trip(name, tmp_path):
    rig = load_rig(RIGS / f"{name}.json")
    path = tmp_path / "copy.json"
    save_rig(rig, path)
    again = load_rig(path)
    assert again.to_dict() == rig.to_dict()
    assert again.digest() == rig.digest()
    for a, b in zip(rig.projectors, again.projectors, strict=True):
        np.testing.assert_array_equal(a.R, b.R)
        np.testing.assert_array_equal(a.t, b.t)
        np.testing.assert_array_equal(a.K, b.K)
        assert a.patterns == b.patterns
    np.testing.assert_array_equal(rig.camera.K, again.camera.K)
    # what is written is exactly the contract: the file parses as the same JSON again
    assert json.loads(path.read_text()) == rig.to_dict()
    assert not list(tmp_path.glob("*.tmp"))


# (case id, base rig, edit, field named in the message)
BAD = [
    ("unknown top-level key", TWO, lambda d: d.update(extra=1), "rig: unknown key 'extra'"),
    ("unknown camera key", TWO, lambda d: d["camera"].update(fx=1), "camera: unknown key 'fx'"),
    ("unknown projector key", TWO, lambda d: proj0(d).update(gamma=2.2),
     "projectors[0]: unknown key 'gamma'"),
    ("unknown pattern key", TWO, lambda d: pat0(d).update(phase=0),
     "projectors[0].patterns[0]: unknown key 'phase'"),
    ("K 2x3", TWO, lambda d: d["camera"].update(K=d["camera"]["K"][:2]), "camera.K"),
    ("projector K 3x2", TWO, lambda d: proj0(d).update(K=[r[:2] for r in proj0(d)["K"]]),
     "projectors[0].K"),
    ("R 3x2", TWO, lambda d: proj0(d).update(R=[r[:2] for r in proj0(d)["R"]]),
     "projectors[0].R"),
    ("t of length 2", TWO, lambda d: proj0(d).update(t=[0.1, 0.2]), "projectors[0].t"),
    ("dist of length 3", TWO, lambda d: d["camera"].update(dist=[0, 0, 0]), "camera.dist"),
    ("projector dist of length 6", TWO, lambda d: proj0(d).update(dist=[0] * 6),
     "projectors[0].dist"),
    ("R not orthonormal", TWO, lambda d: proj0(d).update(R=(2 * np.eye(3)).tolist()),
     "projectors[0].R: expected a rotation"),
    ("R a reflection", TWO, lambda d: proj0(d).update(R=np.diag([1.0, 1, -1]).tolist()),
     "projectors[0].R: expected a rotation"),
    ("missing top-level key", TWO, lambda d: d.pop("projectors"), "rig: missing key 'projectors'"),
    ("missing camera key", TWO, lambda d: d["camera"].pop("K"), "camera: missing key 'K'"),
    ("missing projector key", TWO, lambda d: proj0(d).pop("t"), "projectors[0]: missing key 't'"),
    ("missing pattern key", TWO, lambda d: pat0(d).pop("pitch_px"),
     "projectors[0].patterns[0]: missing key 'pitch_px'"),
    ("wrong format", TWO, lambda d: d.update(format="lightflow-rig/2"), "format"),
    ("unknown kind", TWO, lambda d: pat0(d).update(kind="sine"), "projectors[0].patterns[0].kind"),
    ("unknown channel", TWO, lambda d: pat0(d).update(channel="yellow"),
     "projectors[0].patterns[0].channel"),
    ("pitch too large for W", TWO, lambda d: pat0(d).update(pitch_px=proj0(d)["width"] / 2 + 1),
     "projectors[0].patterns[0].pitch_px: pattern does not fit"),
    ("width >= pitch/2", TWO, lambda d: pat0(d).update(width_px=pat0(d)["pitch_px"] / 2),
     "projectors[0].patterns[0].width_px"),
    ("exp2 lines too many", ONE, lambda d: pat0(d).update(lines=proj0(d)["width"]),
     "projectors[0].patterns[0].lines: pattern does not fit"),
    ("duplicate channels", TWO, lambda d: d["projectors"][1]["patterns"][0].update(channel="red"),
     "projectors: each pattern needs its own colour channel"),
    ("two patterns on one of two projectors", TWO,
     lambda d: proj0(d)["patterns"].append(dict(pat0(d), channel="green")),
     "projectors[0].patterns: expected 1 pattern"),
    ("one pattern on a single projector", ONE, lambda d: proj0(d)["patterns"].pop(),
     "projectors[0].patterns: expected 2 patterns"),
    ("three projectors", TWO, lambda d: d["projectors"].append(copy.deepcopy(proj0(d))),
     "projectors: expected a list of one or two"),
    ("duplicate names", TWO, lambda d: d["projectors"][1].update(name="left"), "projectors"),
    ("camera width 1e12", TWO, lambda d: d["camera"].update(width=10**12),
     "camera.width: expected an integer <= 16384, got 1000000000000"),
    ("projector height 16385", TWO, lambda d: proj0(d).update(height=16385),
     "projectors[0].height: expected an integer <= 16384"),
    ("K entries as strings", TWO, lambda d: d["camera"]["K"][0].__setitem__(0, "1800"),
     'camera.K: expected a 3x3 matrix of numbers, got [["1800"'),
    ("distortion 1e6", TWO, lambda d: d["camera"].update(dist=[1e6, 1e6, 0, 0, 1e6]),
     "camera.dist: coefficients up to 1e+06"),
    ("distortion k1 = 50", TWO, lambda d: proj0(d).update(dist=[50, 0, 0, 0, 0]),
     "projectors[0].dist: coefficients move image points by more than a factor 4"),
    ("width as a huge integer", TWO, lambda d: d["camera"].update(width=10**400),
     "camera.width: expected an integer <= 16384, got"),
    ("camera gamma 9", TWO, lambda d: d["camera"].update(gamma=9),
     "camera.gamma: expected 0.3 to 4 (1: a linear camera), got 9"),
    ("camera gamma a string", TWO, lambda d: d["camera"].update(gamma="srgb"),
     'camera.gamma: expected a number, got "srgb"'),
]  # fmt: skip


def test_camera_gamma_round_trip_and_keeps_the_geometry(tmp_path):
    """``camera.gamma`` is optional (taken as 1, linear); it changes no line position."""
    rig = load_rig(RIGS / "two-projector.json")
    assert rig.camera.gamma is None and "gamma" not in rig.to_dict()["camera"]
    webcam = rig.with_camera_gamma(2.2)
    path = tmp_path / "webcam.json"
    save_rig(webcam, path)
    again = load_rig(path)
    assert again.camera.gamma == 2.2 and json.loads(path.read_text())["camera"]["gamma"] == 2.2
    assert again.digest() != rig.digest()
    assert again.geometry_digest() == rig.geometry_digest()  # the same depth table
    assert again.scaled(0.5).camera.gamma == 2.2


@pytest.mark.parametrize("base, edit, where", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_rig_names_file_and_field(base, edit, where, tmp_path):
    path = write(tmp_path, edited(base, edit))
    with pytest.raises(ConfigError) as info:
        load_rig(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert where in message
    assert "\n" not in message


@pytest.mark.parametrize("base, edit, where", [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_rig_through_cli_is_one_line_exit_2(base, edit, where, tmp_path, capsys):
    path = write(tmp_path, edited(base, edit))
    assert cli_main(["rig", "check", str(path)]) == 2
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1
    assert captured.err.startswith(f"lightflow: error: {path}: ")
    assert where in captured.err
    assert "Traceback" not in captured.err
    assert captured.out == ""


def test_missing_and_malformed_files(tmp_path, capsys):
    missing = tmp_path / "nope.json"
    assert cli_main(["rig", "check", str(missing)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"lightflow: error: {missing}: file not found")
    assert err.count("\n") == 1
    broken = tmp_path / "broken.json"
    broken.write_text("{")
    assert cli_main(["rig", "check", str(broken)]) == 2
    assert capsys.readouterr().err.startswith(f"lightflow: error: {broken}: not valid JSON")


def test_parallel_projectors_are_refused_with_the_reason(tmp_path, capsys):
    path = write(tmp_path, parallel_rig(), "parallel.json")
    load_rig(path)  # a valid file ...
    assert cli_main(["rig", "check", str(path)]) == 2  # ... that cannot measure depth
    captured = capsys.readouterr()
    assert captured.err.count("\n") == 1 and "Traceback" not in captured.err
    assert captured.err.startswith(f"lightflow: error: {path}: projectors: h(z) is flat over ")
    assert "(parallel projectors?)" in captured.err
    assert "no depth can be measured" in captured.err
    # the numbers and the advice still go to stdout
    assert "verdict: degenerate" in captured.out
    assert "move one projector forward or backward" in captured.out


def test_single_projector_with_two_uniform_patterns_is_refused(tmp_path, capsys):
    def edit(d):
        proj0(d)["patterns"] = [
            {"channel": c, "kind": "uniform", "pitch_px": p, "width_px": 3.0, "offset_px": 0.0}
            for c, p in (("red", 24.0), ("blue", 30.0))
        ]

    path = write(tmp_path, edited(ONE, edit))
    assert cli_main(["rig", "check", str(path)]) == 2
    err = capsys.readouterr().err
    assert f"{path}: projectors[0].patterns: h(z) is flat over 100 %" in err


@pytest.mark.parametrize("name", ["two-projector", "single-projector"])
def test_rig_check_of_example_rigs(name, tmp_path, capsys):
    out = tmp_path / "pictures"
    assert cli_main(["rig", "check", str(RIGS / f"{name}.json"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "verdict: usable" in printed
    assert "expected depth error (mm), median" in printed
    names = sorted(p.name for p in out.iterdir())
    assert len(names) == 12 and "error-0.75m.png" in names and "overlap-0.50m.png" in names
    assert cli_main(["rig", "check", str(RIGS / f"{name}.json")]) == 0
    assert "add --out DIR" in capsys.readouterr().out


def test_rig_check_speaks_plain_words(capsys):
    """No explanatory line passes for a failure; the paper's symbols come with words."""
    assert cli_main(["rig", "check", "two-projector", "--stride", "32"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert not [line for line in out if line.lower().startswith("error")]
    text = "\n".join(out)
    for words in ("working depth z", "lit by both projectors", "steepness |dh/dz| (1/m)",
                  "expected depth error (mm)", "line spacing B1 in the image (px)",
                  "h(z) is the log ratio of the two light flows"):
        assert words in text, words
    assert "verdict: usable" in out
