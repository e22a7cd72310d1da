"""The plotting module: every figure writes a non-blank PNG of its size; the surface painter and the
error colours are checked pixel by pixel on surfaces whose picture is known."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.image import imread

from lungdeform.plot.breathing import breathing_volume, pv_loop, residuals
from lungdeform.plot.figure import png_bytes, save_png
from lungdeform.plot.fit import bounding_box, cumulative_errors, direction_field, fit_history, ray_histogram
from lungdeform.plot.motion import motion
from lungdeform.plot.paper import circular_figure, convergence_figure, planar_figure
from lungdeform.plot.segmentation import label_overlay
from lungdeform.plot.statistics import ScatterPanel, StripPanel, grouped_bars, scatter_grid, strip_boxes
from lungdeform.plot.surface import error_colours, error_map, merge_surfaces, project, shade, snapshot
from tests.conftest import ellipsoid_lung


def _square(x0: float, y: float, size: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """A square in the plane y = ``y`` from x = ``x0``, z = 0, wound so that its normal is −y (it faces
    the viewer of the anterior view)."""
    v = np.array([[x0, y, 0.0], [x0 + size, y, 0.0], [x0 + size, y, size], [x0, y, size]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def _pixel(path, ax, x: float, y: float) -> np.ndarray:
    """RGB in [0, 1] of the PNG at ``path`` where the data point (x, y) of ``ax`` was drawn."""
    img = imread(path)
    px, py = ax.transData.transform((x, y))
    return img[int(round(img.shape[0] - py)), int(round(px)), :3]


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
        "error_map": (lambda: error_map(v, f, err, title="t"), (1080, 414)),
        "cumulative_errors": (lambda: cumulative_errors({"a": err, "b": 2 * err}), (810, 378)),
        "ray_histogram": (lambda: ray_histogram(np.array([1, 3, 2]), np.array([-1.0, 0, 1, 2])), (560, 280)),
        "bounding_box": (lambda: bounding_box(bb), (880, 320)),
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
                                               "right": {"a": 1.5, "b": 3.0}}, title="t", ylabel="mm"), (550, 352)),
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


def test_error_map_colours_each_face_by_its_error(tmp_path):
    # truth: two flat squares facing the anterior viewer (Lambert term 1, so no darkening), errors
    # 1 mm and 3 mm on a 0…4 mm scale: their centres show viridis at 1/4 and 3/4
    (va, fa), (vb, fb) = _square(0.0, 0.0), _square(20.0, 0.0)
    v, f = merge_surfaces([(va, fa), (vb, fb)])
    error = np.r_[np.full(4, 1.0), np.full(4, 3.0)]
    fig = error_map(v, f, error, views=("anterior",), vmax=4.0)
    path = save_png(fig, tmp_path / "map.png")
    viridis = colormaps["viridis"]
    for x, value in ((5.0, 1.0), (25.0, 3.0)):
        assert _pixel(path, fig.axes[0], x + 2.0, 3.0) == pytest.approx(viridis(value / 4.0)[:3], abs=2 / 255)


def test_error_colours_scale_clip_and_mark_missing():
    # truth: the colour scale is linear on [0, vmax]; above it the top colour; NaN grey (0.6)
    viridis = colormaps["viridis"]
    got = error_colours(np.array([0.0, 2.0, 4.0, 9.0, np.nan]), vmax=4.0)
    assert got[:4] == pytest.approx(np.array([viridis(0.0), viridis(0.5), viridis(1.0), viridis(1.0)])[:, :3])
    assert got[4] == pytest.approx([0.6, 0.6, 0.6])


def test_project_culls_back_faces_and_orders_far_first():
    # truth: of two squares facing the anterior viewer (who looks from −y) the one at y = 50 is
    # farther than the one at y = 0, so it is painted first; a square wound the other way faces away
    near, far = _square(0.0, 0.0), _square(0.0, 50.0)
    back_v, back_f = _square(0.0, 20.0)
    v, f = merge_surfaces([near, far, (back_v, back_f[:, ::-1])])
    polygons, cosine, index = project(v, f, "anterior")
    assert sorted(index) == [0, 1, 2, 3]  # the reversed square (faces 4, 5) is culled
    assert set(index[:2]) == {2, 3}  # the far square first
    assert cosine == pytest.approx(np.ones(4))  # both face the viewer squarely
    # anterior view: image right = +x (patient left), image up = +z
    assert polygons[:, :, 0].max() == 10.0 and polygons[:, :, 1].max() == 10.0


def test_shade_is_lambert_with_ambient():
    # truth: ambient 0.25 → a face at 60° (cos 0.5) gets 0.25 + 0.75·0.5 = 0.625 of its colour,
    # a face facing the light keeps its colour
    rgb = np.array([[1.0, 0.5, 0.2], [1.0, 0.5, 0.2]])
    assert shade(rgb, np.array([0.5, 1.0]), ambient=0.25) == pytest.approx(np.array([0.625, 1.0])[:, None] * rgb)


def test_snapshot_later_layer_covers_earlier(tmp_path):
    # truth: a red square under a blue one of the same place: the blue one, drawn later, is what shows;
    # beside it only the red one (the "rim" the demo shows)
    red, blue = _square(0.0, 0.0, 20.0), _square(0.0, -5.0, 10.0)
    fig = snapshot([([red], "#ff0000", 1.0), ([blue], "#0000ff", 1.0)], views=("anterior",))
    path = save_png(fig, tmp_path / "s.png")
    assert _pixel(path, fig.axes[0], 5.0, 5.0) == pytest.approx([0, 0, 1], abs=2 / 255)
    assert _pixel(path, fig.axes[0], 15.0, 5.0) == pytest.approx([1, 0, 0], abs=2 / 255)


def test_merge_surfaces_renumbers_faces():
    # truth: the second mesh's faces move past the first mesh's 4 vertices
    a, b = _square(0.0, 0.0), _square(20.0, 0.0)
    v, f = merge_surfaces([a, b])
    assert v.shape == (8, 3) and f.tolist() == [[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]]


def test_cumulative_errors_orders_methods_and_marks_medians():
    # truth: medians of [1, 2, 3] and [0.5, 0.5, 0.5] are 2 and 0.5; methods listed by median; each
    # curve climbs from 0 to 1
    fig = cumulative_errors({"worse": np.array([1.0, 2.0, 3.0]), "better": np.array([0.5, 0.5, np.nan])})
    ax = fig.axes[0]
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    assert labels == ["better (median 0.50 mm)", "worse (median 2.00 mm)"]
    lines = ax.get_lines()  # per method its curve then its median dot, methods in legend order
    assert lines[0].get_ydata()[0] == 0.0 and lines[0].get_ydata()[-1] == pytest.approx(1.0)
    assert lines[1].get_xydata().tolist() == [[0.5, 0.5]] and lines[3].get_xydata().tolist() == [[2.0, 0.5]]


def test_no_pyplot_and_no_backend_choice():
    # the Figure + Agg canvas route must never load pyplot (global state, a GUI backend): checked in
    # a fresh interpreter, where nothing else could have loaded it
    code = ("import sys, numpy as np; from lungdeform.plot.figure import png_bytes; "
            "from lungdeform.plot.fit import fit_history; png_bytes(fit_history({'a': np.arange(3.0)})); "
            "assert 'matplotlib.pyplot' not in sys.modules, 'pyplot loaded'")
    subprocess.run([sys.executable, "-c", code], check=True)
