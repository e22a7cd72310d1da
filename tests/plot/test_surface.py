"""The surface painter and the error colours (lungdeform.plot.surface), checked pixel by pixel on
surfaces whose picture is known."""

from __future__ import annotations

import numpy as np
import pytest
from matplotlib import colormaps
from matplotlib.image import imread

from lungdeform.plot.figure import PixelImage, save_png
from lungdeform.plot.surface import error_colours, error_map, error_maps, merge_surfaces, project, shade, snapshot


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


def test_error_maps_one_row_per_surface_on_one_scale(tmp_path):
    # truth: the same square at two targets, 1 mm then 3 mm from it everywhere; with no vmax the scale
    # is the 98th percentile of both rows (3 mm), so row 1 shows viridis at 1/3 and row 2 its top;
    # one colour bar for the figure (two panels and the bar)
    v, f = _square(0.0, 0.0)
    fig = error_maps([(v, np.full(4, 1.0)), (v + [0.0, 0.0, 5.0], np.full(4, 3.0))], f, views=("anterior",),
                     row_titles=["inhale", "exhale"])
    path = save_png(fig, tmp_path / "maps.png")
    viridis = colormaps["viridis"]
    assert len(fig.axes) == 3
    assert _pixel(path, fig.axes[0], 7.0, 3.0) == pytest.approx(viridis(1.0 / 3.0)[:3], abs=2 / 255)
    assert _pixel(path, fig.axes[1], 7.0, 8.0) == pytest.approx(viridis(1.0)[:3], abs=2 / 255)
    assert fig.axes[0].get_title() == "inhale: anterior" and fig.axes[1].get_title() == "exhale"


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


def test_error_maps_of_many_rows_say_their_common_size_instead_of_ticks(tmp_path):
    # truth: three 10 mm squares side by side in rows; panels are the largest extent × 1.06 (10.6 mm)
    # across and up; from three rows on no ticks, the size in the title; the panels are one image
    # drawn on the figure (no Axes per panel: the only Axes is the colour bar) and the PNG shows each
    # square at its panel's centre in its colour (1 mm on a 0…4 mm scale: viridis at 1/4)
    v, f = _square(0.0, 0.0)
    fig = error_maps([(v, np.full(4, 1.0))] * 3, f, views=("anterior",), title="t", vmax=4.0)
    assert fig._suptitle.get_text() == "t; every panel 11 × 11 mm"
    assert len(fig.axes) == 1 and fig.axes[0].get_ylabel() == "distance to the target surface (mm)"
    img = imread(save_png(fig, tmp_path / "maps.png"))
    image, = (a for a in fig.artists if isinstance(a, PixelImage))
    h, w = image._rgba.shape[:2]
    c0, r0 = image._top_left
    rows = r0 + h * np.array([1, 3, 5]) // 6  # the three panels' centres, one below the other
    assert img[rows, c0 + w // 2, :3] == pytest.approx(np.tile(colormaps["viridis"](0.25)[:3], (3, 1)), abs=2 / 255)


def _side_px(img: np.ndarray, rgb) -> float:
    """The side (pixels) of a square drawn in colour ``rgb``: the root of the count of its pixels."""
    return float(np.sqrt((np.abs(img[..., :3] - rgb) < 2.5 / 255).all(axis=2).sum()))


@pytest.mark.parametrize("rows", [2, 3])
def test_error_maps_draw_every_panel_to_the_same_mm_per_pixel(tmp_path, rows):
    # truth: squares of 20, 40 and 10 mm in their own rows (errors 1, 2, 3 mm on a 0…4 mm scale, so
    # viridis at 1/4, 1/2, 3/4; unshaded, facing the viewer): each panel is centred on its own square
    # but all share one scale, the largest square's panel (40 × 1.06 mm) fitted to the panel box
    # (2.6 inch at 80 dpi = 208 pixels from three rows on; else 3.2 inch at 90 dpi = 288 pixels
    # across, the narrower side of its box): each square's side in pixels (the root of its fully
    # covered pixels, short of the true side by at most the two partly covered edges) is its mm over
    # that one mm per pixel
    sides = [20.0, 40.0, 10.0][:rows]
    surfaces = [(_square(0.0, 0.0, side)[0], np.full(4, k + 1.0)) for k, side in enumerate(sides)]
    fig = error_maps(surfaces, _square(0.0, 0.0)[1], views=("anterior",), vmax=4.0)
    img = imread(save_png(fig, tmp_path / "maps.png"))
    img = img[:, : int(fig.axes[-1].get_position().x0 * img.shape[1])]  # the colour bar shows every colour: left out
    mm_per_pixel = 40.0 * 1.06 / (208 if rows > 2 else 288)
    for k, side in enumerate(sides):
        assert side / mm_per_pixel - 2.0 <= _side_px(img, colormaps["viridis"]((k + 1) / 4.0)[:3]) <= side / mm_per_pixel + 1.0


def test_error_maps_grey_where_the_error_is_missing(tmp_path):
    # truth: a face whose vertices' errors are NaN (not measured) is grey 0.6, on every path: an Axes
    # per panel (one row) and one image (three rows)
    v, f = _square(0.0, 0.0, 20.0)
    for rows in (1, 3):
        fig = error_maps([(v, np.full(4, np.nan))] * rows, f, views=("anterior",), vmax=1.0)
        img = imread(save_png(fig, tmp_path / f"grey{rows}.png"))
        img = img[:, : int(fig.axes[-1].get_position().x0 * img.shape[1])]
        assert _side_px(img, [0.6, 0.6, 0.6]) > 50
