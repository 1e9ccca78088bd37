"""report.html is one self-contained file that a real browser renders with its tables and figures:
headless Chromium (Debian package `chromium`; `.ci/run` installs it) takes a screenshot, and the
test finds the table's ruled cells and the figure's coloured curve in its pixels."""

import os
import pathlib
import shutil
import subprocess

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pytest

from hdjax._workflows.html import markdown_to_html, write_report_html


def _chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    if os.environ.get("CI"):
        pytest.fail("headless Chromium is required in CI (.ci/run installs the Debian package `chromium`)")
    pytest.skip("no chromium on this machine (install the Debian package `chromium`); CI installs it and runs it")


def screenshot(html: pathlib.Path, png: pathlib.Path, *, width: int = 1000, height: int = 1400) -> np.ndarray:
    """Render `html` with headless Chromium into `png` and return the RGB pixels (H, W, 3) in 0–1."""
    exe = _chromium()
    profile = png.parent / "chromium-profile"
    cmd = [exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
           "--disable-background-networking", "--disable-component-update", "--disable-sync",
           "--hide-scrollbars", f"--user-data-dir={profile}", f"--screenshot={png}",
           f"--window-size={width},{height}", html.resolve().as_uri()]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert png.is_file(), f"chromium wrote no screenshot (exit {r.returncode}): {r.stderr[-2000:]}"
    return plt.imread(png)[..., :3]


def _report(folder: pathlib.Path) -> pathlib.Path:
    fig, ax = plt.subplots(figsize=(5, 3))
    t = np.linspace(0, 1, 200)
    ax.plot(t, np.sin(2 * np.pi * t), color=(0.85, 0.1, 0.1), lw=6)
    fig.savefig(folder / "fig3_hysteresis.png", dpi=100)
    plt.close(fig)
    rows = "\n".join(f"| K{k} | {1000 + k} | N·m/rad |" for k in range(6))
    (folder / "report.md").write_text(
        "# Identification of `hd2`\n\nA **table** and a figure.\n\n"
        f"| parameter | value | unit |\n|---|---|---|\n{rows}\n\n"
        "## Figures\n\n![fig3_hysteresis.png](fig3_hysteresis.png)\n", encoding="utf-8")
    return folder / "report.md"


def test_report_html_is_self_contained(tmp_path):
    html = write_report_html(_report(tmp_path)).read_text()
    assert html.startswith("<!DOCTYPE html>") and "<table>" in html and "<th>parameter</th>" in html
    assert 'src="data:image/png;base64,' in html
    assert "http://" not in html and "https://" not in html  # nothing fetched from the network
    # a missing figure stays a link with its alt text, never an error
    assert 'src="gone.png"' in markdown_to_html("![gone](gone.png)", tmp_path)


def test_report_html_renders_in_headless_chromium(tmp_path):
    report = _report(tmp_path)
    html = write_report_html(report)
    # moved away from its figures: the page must not need them
    lone = tmp_path / "elsewhere"
    lone.mkdir()
    shutil.copy(html, lone / "report.html")
    (tmp_path / "fig3_hysteresis.png").unlink()
    img = screenshot(lone / "report.html", tmp_path / "shot.png")
    red = (img[..., 0] > 0.7) & (img[..., 1] < 0.3) & (img[..., 2] < 0.3)
    assert red.sum() > 2000, f"the embedded figure's red curve is not visible ({red.sum()} px)"
    # table: the header row's grey fill (#f0f3f6) and the cell borders (#d0d7de) are drawn
    header = np.all(np.abs(img - np.array([0xF0, 0xF3, 0xF6]) / 255) < 0.02, axis=-1)
    border = np.all(np.abs(img - np.array([0xD0, 0xD7, 0xDE]) / 255) < 0.03, axis=-1)
    assert header.sum() > 1000, "the table header is not rendered"
    rows_with_border = np.flatnonzero(border.sum(axis=1) > 150)  # horizontal rules across the table
    assert len(rows_with_border) >= 7, "the table rows are not ruled"
    # the figure sits below the table
    assert np.flatnonzero(red.any(axis=1)).min() > rows_with_border.min()
