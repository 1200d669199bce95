"""Figures of the paper reproduction, and the shared plotting helpers' errors."""

from __future__ import annotations

import sys

import pytest

from pose_daemon.cli import main
from pose_daemon.errors import UserError
from pose_daemon.paper.figures import UNICYCLE_FILES
from pose_daemon.plotting import check_plot_path, require_matplotlib

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_sweep_plot_is_written(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    path = tmp_path / "fig4.png"
    argv = ["paper", "sweep", "--step-deg", "15", "--no-progress", "--plot", str(path)]
    assert main(argv) == 0
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC) and len(data) > 20_000
    assert f"wrote {path}" in capsys.readouterr().err


def test_unicycle_plots_are_written(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "figs" / "noisy"
    argv = ["paper", "unicycle", "--duration", "3", "--noise-px", "0.5", "--plot", str(out)]
    assert main(argv) == 0
    for name in UNICYCLE_FILES:
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 15_000, name


def test_plot_into_a_missing_directory_is_a_user_error(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    path = tmp_path / "nowhere" / "fig4.png"
    assert main(["paper", "sweep", "--limit", "10", "--plot", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "does not exist" in err and str(path) in err
    assert not path.exists()


def test_plot_with_an_unknown_suffix_is_a_user_error(tmp_path) -> None:
    with pytest.raises(UserError, match="must end in one of .png"):
        check_plot_path(tmp_path / "fig4.txt")


def test_unicycle_plot_dir_that_is_a_file_is_a_user_error(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    target = tmp_path / "file"
    target.write_text("x")
    assert main(["paper", "unicycle", "--duration", "0.5", "--plot", str(target)]) == 2
    assert "is not a directory" in capsys.readouterr().err


def test_missing_matplotlib_says_how_to_install_it(monkeypatch, tmp_path, capsys) -> None:
    # None in sys.modules makes the import fail as if matplotlib were not installed.
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(UserError) as exc:
        require_matplotlib()
    assert str(exc.value) == "plots need matplotlib: pip install 'pose-daemon[plot]'"
    assert main(["paper", "sweep", "--limit", "10", "--plot", str(tmp_path / "a.png")]) == 2
    assert "pip install 'pose-daemon[plot]'" in capsys.readouterr().err


def test_figure_helpers_write_each_format(tmp_path) -> None:
    pytest.importorskip("matplotlib")
    from pose_daemon.plotting import check_plot_dir, new_figure, save_figure

    out = check_plot_dir(tmp_path / "a" / "b")
    assert out.is_dir()
    fig, axes = new_figure(2, 3)
    assert axes.shape == (2, 3)
    axes[0, 0].plot([0, 1], [1, 0])
    svg = save_figure(fig, out / "grid.svg")
    assert svg.read_text().lstrip().startswith("<?xml")
    fig, ax = new_figure()
    ax.plot([0, 1], [0, 1])
    pdf = save_figure(fig, out / "line.pdf")
    assert pdf.read_bytes().startswith(b"%PDF")
