"""Every figure of lungdeform.plot writes a non-blank PNG of its size, atomically, without pyplot
(lungdeform.plot.figure)."""

from __future__ import annotations

import io
import subprocess
import sys

import numpy as np
import pytest
from matplotlib.image import imread

from lungdeform.plot.breathing import breathing_volume, pv_loop, residuals
from lungdeform.plot.figure import PixelImage, new_figure, png_bytes, save_png
from lungdeform.plot.fit import (bounding_box, cumulative_errors, cumulative_panels, direction_field, fit_history,
                                 ray_histogram, target_errors)
from lungdeform.plot.motion import motion
from lungdeform.plot.paper import circular_figure, convergence_figure, planar_figure
from lungdeform.plot.segmentation import label_overlay
from lungdeform.plot.statistics import ScatterPanel, StripPanel, grouped_bars, scatter_grid, strip_boxes
from lungdeform.plot.surface import error_map, error_maps, snapshot
from tests.conftest import ellipsoid_lung


def _figures(rng):
    lung = ellipsoid_lung("right", subdivisions=2)
    v, f = lung.vertices, lung.faces
    err = rng.random(len(v))
    bb = {"model": [{"volume_ml": 1500.0 + 50 * k, "dims_mm": [90 + k, 140 + k, 220 + k], "ratio": 0.52}
                    for k in range(3)],
          "observed": [{"volume_ml": 1500.0, "dims_mm": [90, 140, 220], "ratio": 0.52}]}
    ct = rng.normal(-500, 300, (40, 50))
    lab = np.zeros((40, 50), int)
    lab[10:30, 5:20], lab[10:30, 30:45] = 1, 2
    t = np.linspace(0, 8, 200)
    grid_v = np.array([[x, y, 0.0] for y in range(5) for x in range(5)], float)
    grid_f = np.array([[i + 5 * j, i + 1 + 5 * j, i + 6 + 5 * j] for j in range(4) for i in range(4)]
                      + [[i + 5 * j, i + 6 + 5 * j, i + 5 + 5 * j] for j in range(4) for i in range(4)])
    bump = np.sin(np.pi * grid_v[:, 0] / 4) * np.sin(np.pi * grid_v[:, 1] / 4)
    groups = [rng.normal(1, 0.1, 5), rng.normal(2, 0.1, 4)]
    return {
        "snapshot": (lambda: snapshot([([(v, f)], "#4a7ab5", 1.0)], views=("anterior", "superior")), (924, 528)),
        "error_map": (lambda: error_map(v, f, err, title="t"), (1188, 418)),
        "error_maps": (lambda: error_maps([(v, err), (v * 1.1, err), (v, 2 * err)], f, row_titles=["a", "b", "c"]),
                       (912, 788)),
        "cumulative_errors": (lambda: cumulative_errors({"a": err, "b": 2 * err}), (810, 373)),
        "cumulative_panels": (lambda: cumulative_panels({"p": {"a": err}, "q": {"a": err, "b": 2 * err}, "r": {}}),
                              (1312, 552)),
        "target_errors": (lambda: target_errors({"p": {"a": err}, "q": {"a": err, "b": 2 * err}, "r": {"b": err}}),
                          (1312, 316)),
        "ray_histogram": (lambda: ray_histogram(np.array([1, 3, 2]), np.array([-1.0, 0, 1, 2])), (560, 280)),
        "bounding_box": (lambda: bounding_box(bb), (960, 320)),
        "direction_field": (lambda: direction_field(v, lung.vertices / 100.0, err), (880, 400)),
        "fit_history": (lambda: fit_history({"optimizer": np.linspace(3, 1, 20)}), (560, 280)),
        "label_overlay": (lambda: label_overlay([(ct, lab, 1.0, "axial"), (ct, lab, 1.5, "coronal")], "t"),
                          (756, 414)),
        "motion": (lambda: motion(rng.normal(size=(6, 2, 3)), np.arange(6.0), "time (s)", ["a", "b"]), (1210, 374)),
        "breathing_volume": (lambda: breathing_volume(t, 2400 + 250 * np.sin(t), "t", data=(t, 2400 + np.cos(t)),
                                                      held_out_from=4.0), (1100, 396)),
        "pv_loop": (lambda: pv_loop(np.sin(t), 2400 + np.cos(t), "t"), (528, 462)),
        "residuals": (lambda: residuals(t, np.sin(t), "t"), (1100, 330)),
        "strip_boxes": (lambda: strip_boxes([StripPanel("c1", groups, ["left", "right"], [1.0, 2.0])] * 2,
                                            ["tab:blue", "tab:orange"], rows=1, cols=2, title="t",
                                            rng=np.random.default_rng(0)), (704, 286)),
        "scatter_grid": (lambda: scatter_grid([ScatterPanel("c1", {"left": rng.random((4, 2))}, identity=True,
                                                            legend=True)], {"left": "tab:blue"},
                                                rows=1, cols=1, title="t"), (352, 286)),
        "planar_figure": (lambda: planar_figure(grid_v, grid_f, bump, bump * 1.001, 0.1), (1500, 480)),
        "circular_figure": (lambda: circular_figure(grid_v - 2.0, grid_f, 1.0 + bump, np.c_[bump, bump, 0 * bump],
                                                    bump + 0.1, 0.5, 0.6), (1200, 540)),
        "convergence_figure": (lambda: convergence_figure(np.arange(5.0), 10.0 ** -np.arange(5.0),
                                                          10.0 ** -np.arange(8.0), 10.0 ** -np.arange(8.0),
                                                          tol=1e-6, n_nodes=100, title="t"), (800, 550)),
        "grouped_bars": (lambda: grouped_bars({"left": {"a": 1.0, "b": 2.0, "c": np.nan},
                                               "right": {"a": 1.5, "b": 3.0}}, title="t", ylabel="mm"), (550, 374)),
        # 30 groups (validate single-scan's per-axis figure of ten lungs): the legend under the axes in
        # 4 columns, 8 rows; inside the axes it did not fit and matplotlib warned (an error here)
        "grouped_bars_30": (lambda: grouped_bars({f"copd{k} {r}": {"LR": 1.0, "AP": 2.0, "SI": 3.0}
                                                  for k in range(10) for r in ("observed", "default", "paper")},
                                                 title="t", ylabel="mm"), (550, 528)),
    }


@pytest.mark.parametrize("name", sorted(_figures(np.random.default_rng(0))))
def test_every_figure_writes_a_nonblank_png_of_its_size(name, tmp_path, rng):
    build, (width, height) = _figures(rng)[name]
    path = save_png(build(), tmp_path / f"{name}.png")
    img = imread(path)
    # the size is the figure's inches × its dpi (saved at the figure's own dpi, no cropping)
    assert img.shape[:2] == (height, width)
    # drawn on: a good share of the pixels is not the white background
    assert (img[..., :3] < 0.9).any(axis=2).mean() > 0.01
    assert not list(tmp_path.glob(".*"))  # written atomically: no temporary left


def test_no_pyplot_and_no_backend_choice():
    # the Figure + Agg canvas route must never load pyplot (global state, a GUI backend): checked in
    # a fresh interpreter, where nothing else could have loaded it
    code = ("import sys, numpy as np; from lungdeform.plot.figure import png_bytes; "
            "from lungdeform.plot.fit import fit_history; png_bytes(fit_history({'a': np.arange(3.0)})); "
            "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot loaded'")
    subprocess.run([sys.executable, "-c", code], check=True)


def test_png_bytes_are_matplotlibs_pixels_rgb_when_opaque(tmp_path):
    # truth: matplotlib's own PNG writer (savefig) on the same figure: the same pixels; an opaque
    # figure (every pixel's alpha 255 there) is written RGB, a transparent one keeps its alpha
    fig = fit_history({"optimizer": np.linspace(3, 1, 20)})
    ours = imread(io.BytesIO(png_bytes(fig)))
    fig.savefig(tmp_path / "mpl.png", format="png", dpi="figure")
    theirs = imread(tmp_path / "mpl.png")
    assert ours.shape[2] == 3 and (theirs[..., 3] == 1.0).all()
    assert np.array_equal(ours, theirs[..., :3])
    fig.patch.set_alpha(0.0)
    clear = imread(io.BytesIO(png_bytes(fig)))
    assert clear.shape[2] == 4 and (clear[..., 3] < 1.0).any()


def test_pixel_image_is_drawn_pixel_for_pixel_and_scaled_at_another_dpi(tmp_path, rng):
    # truth: the image's own pixels, at its place (top-left pixel (30, 20) of a 200 × 100 figure) at
    # the figure's dpi; saved at twice the dpi, each pixel becomes 2 × 2 at twice the offset; a
    # vector backend gets the image too
    rgba = rng.integers(0, 256, (7, 11, 4)).astype(np.uint8)
    rgba[..., 3] = 255
    fig = new_figure(2.0, 1.0, dpi=100)
    fig.add_artist(PixelImage(rgba, (30, 20), fig.dpi))
    img = np.rint(imread(io.BytesIO(png_bytes(fig)))[..., :3] * 255)
    assert np.array_equal(img[20:27, 30:41], rgba[..., :3])
    assert (img[:20] == 255).all() and (img[27:] == 255).all()
    fig.savefig(tmp_path / "x2.png", dpi=200)
    big = np.rint(imread(tmp_path / "x2.png") * 255)
    assert np.array_equal(big[40:54:2, 60:82:2, :3], rgba[..., :3]) and np.array_equal(big[41:54:2, 61:82:2, :3],
                                                                                          rgba[..., :3])
    svg = io.BytesIO()
    fig.savefig(svg, format="svg")
    assert b"<image" in svg.getvalue()
