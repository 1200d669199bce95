"""``pose-daemon estimate``: JSON lines in, one pose object per line out, bad lines reported."""

from __future__ import annotations

import io
import json
import subprocess
import sys

import numpy as np
import pytest

from pose_daemon import Camera, Marker, estimate_pose, geometry
from pose_daemon.cli import main
from pose_daemon.config import Config


def _default_models():
    cfg = Config.default()
    return cfg.camera.model(), cfg.marker.model()


def _corners(camera: Camera, marker: Marker, t=(0.05, -0.02, 1.2)) -> list:
    R = geometry.R_cam_marker_from_R_cam_unrot(geometry.R_cam_unrot_from_paper_angles(0.2, -0.3, 0.1))
    return camera.project(marker.object_points @ R.T + np.array(t)).tolist()


def test_estimate_lines_from_a_file(tmp_path, capsys):
    camera, marker = _default_models()
    good = _corners(camera, marker)
    src = tmp_path / "corners.jsonl"
    src.write_text(
        "\n".join(
            [
                json.dumps({"corners": good, "frame": 7, "t": 1.5}),
                json.dumps({"corners": good[:3]}),
                "{broken",
                "",
                json.dumps({"frame": 9}),
                json.dumps({"corners": [good[0], good[2], good[1], good[3]], "frame": 10}),
                json.dumps([1, 2]),
            ]
        )
        + "\n"
    )
    assert main(["estimate", str(src)]) == 0
    lines = [json.loads(s) for s in capsys.readouterr().out.splitlines()]
    assert len(lines) == 6
    first = lines[0]
    assert first["ok"] is True and first["frame"] == 7 and first["t"] == 1.5
    expected = estimate_pose(good, camera, marker)
    assert np.allclose(first["tvec"], expected.tvec, atol=1e-12)
    assert np.allclose(first["tvec"], (0.05, -0.02, 1.2), atol=1e-8)
    for key in (
        "rvec",
        "camera_position",
        "alpha_deg",
        "beta_deg",
        "gamma_deg",
        "reprojection_error_px",
        "ambiguity_ratio",
        "corners",
    ):
        assert key in first
    assert lines[1] == {"ok": False, "error": lines[1]["error"]} and "shape (4, 2)" in lines[1]["error"]
    assert lines[2]["ok"] is False and lines[2]["error"].startswith("line 3: not JSON")
    assert lines[3] == {"frame": 9, "ok": False, "error": 'line 5: no "corners" key'}
    assert lines[4]["frame"] == 10 and "bow-tie" in lines[4]["error"] and "rvec" not in lines[4]
    assert "JSON object" in lines[5]["error"]


def test_estimate_with_config_and_method(tmp_path, capsys):
    cfg = tmp_path / "cam.toml"
    cfg.write_text(
        '[camera]\nsource = "synthetic"\nwidth = 640\nheight = 480\nfx = 500.0\nfy = 500.0\n'
        "cx = 320.0\ncy = 240.0\n[marker]\nwidth = 0.3\nheight = 0.15\n"
        '[estimator]\nmethod = "paper"\n'
    )
    camera = Camera(fx=500.0, fy=500.0, cx=320.0, cy=240.0)
    marker = Marker(0.3, 0.15)
    src = tmp_path / "in.jsonl"
    src.write_text(json.dumps({"corners": _corners(camera, marker, (0.1, 0.0, 2.0))}) + "\n")
    try:
        code = main(["estimate", "--config", str(cfg), str(src)])
    except SystemExit as exc:  # a config the schema refuses would exit 2 here
        pytest.fail(f"config refused: {exc}")
    assert code == 0
    out = json.loads(capsys.readouterr().out)
    assert out["ok"] is True and np.allclose(out["tvec"], (0.1, 0.0, 2.0), atol=1e-8)


def test_estimate_user_errors_exit_2(tmp_path, capsys):
    assert main(["estimate", str(tmp_path / "missing.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "missing.jsonl" in err and "cannot read" in err and len(err.strip().splitlines()) == 1
    bad = tmp_path / "bad.toml"
    bad.write_text("[estimator]\nmethod = 3\n")
    assert main(["estimate", "--config", str(bad), str(tmp_path / "x")]) == 2
    assert "bad.toml" in capsys.readouterr().err


def test_estimate_reads_stdin_as_a_subprocess():
    camera, marker = _default_models()
    text = (
        json.dumps({"corners": _corners(camera, marker), "id": "a"})
        + "\n"
        + '{"corners": [[0, 0], [0, 0], [0, 0], [0, 0]]}\n'
    )
    proc = subprocess.run(
        [sys.executable, "-m", "pose_daemon", "estimate"], input=text, capture_output=True, text=True, timeout=60
    )
    assert proc.returncode == 0, proc.stderr
    out = [json.loads(s) for s in io.StringIO(proc.stdout)]
    assert out[0]["ok"] is True and out[0]["id"] == "a"
    assert out[1]["ok"] is False and "same point" in out[1]["error"]


def test_bench_estimator_json_small(capsys):
    assert main(["bench", "estimator", "--n", "40", "--timing-n", "5", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["n"] == 40 and [row["noise_px"] for row in res["levels"]] == [0.0, 0.25, 0.5, 1.0]
    clean = res["levels"][0]
    # Noise-free targets: rotation < 1e-6 deg, translation < 1e-8 relative (1e-6 %).
    assert clean["iterative+polish"]["rot_max_deg"] < 1e-6
    assert clean["iterative"]["trans_p95_pct"] < 1e-6
    for row in res["levels"]:
        for name in ("paper", "paper+polish", "iterative", "iterative+polish", "IPPE_SQUARE", "IPPE_SQUARE+LM"):
            assert 0.0 <= row[name]["flip_rate"] <= 1.0
    assert res["us_per_call"]["iterative+polish"] > 0 and res["batch_poses_per_s"] > 0


def test_bench_estimator_refuses_tiny_n(capsys):
    assert main(["bench", "estimator", "--n", "3"]) == 2
    assert "--n must be at least 10" in capsys.readouterr().err
