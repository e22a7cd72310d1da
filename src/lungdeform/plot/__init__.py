"""Every figure the package draws: matplotlib's object-oriented API on the Agg canvas, one module per
kind of figure.

Each figure function builds and returns a :class:`matplotlib.figure.Figure` on its own canvas
(:func:`lungdeform.plot.figure.new_figure`); :func:`~lungdeform.plot.figure.save_png` writes one
atomically and :func:`~lungdeform.plot.figure.png_bytes` returns its bytes. No pyplot and no
``matplotlib.use``: nothing here keeps global state.

Owns:
- :mod:`~lungdeform.plot.figure`: a Figure on its own Agg canvas, PNG bytes and files, an image drawn
  pixel for pixel;
- :mod:`~lungdeform.plot.raster`: flat triangles filled into an RGBA image, far first, anti-aliased (numba);
- :mod:`~lungdeform.plot.surface`: lung surfaces by a small painter (:func:`snapshot`, :func:`error_map`);
- :mod:`~lungdeform.plot.fit`: the fit report's plots (error distributions, ray hits, bounding boxes,
  the direction field, the search's history);
- :mod:`~lungdeform.plot.segmentation`: the segmentation overlay on CT slices;
- :mod:`~lungdeform.plot.motion`: tracked points' displacement;
- :mod:`~lungdeform.plot.breathing`: breathing curves and their prediction;
- :mod:`~lungdeform.plot.statistics`: cohort and per-method statistics (box-and-strip, scatter, bars);
- :mod:`~lungdeform.plot.paper`: the paper's Figs. 7–9.

May import: :mod:`lungdeform.atomic` only (and numpy, numba, matplotlib and its Pillow): every layer
above may draw. The package imports none of its modules: a caller imports the one it draws with, so
only code that draws imports matplotlib.
"""

#: The names of ``lungdeform/plot.py`` (≤ 0.7) → the module of the package that holds each now.
MOVED = {
    **dict.fromkeys(("new_figure", "png_bytes", "save_png"), "figure"),
    **dict.fromkeys(("VIEWS", "VIEW_DIRECTIONS", "project", "shade", "merge_surfaces", "snapshot",
                     "error_colours", "error_map"), "surface"),
    **dict.fromkeys(("cumulative_errors", "ray_histogram", "bounding_box", "direction_field", "fit_history"), "fit"),
    **dict.fromkeys(("OVERLAY_COLOURS", "label_overlay"), "segmentation"),
    "motion": "motion",
    **dict.fromkeys(("breathing_volume", "pv_loop", "residuals", "prediction_errors", "prediction_excerpt"),
                    "breathing"),
    **dict.fromkeys(("panel_grid", "StripPanel", "strip_boxes", "ScatterPanel", "scatter_grid", "grouped_bars"),
                    "statistics"),
    **dict.fromkeys(("planar_figure", "circular_figure", "convergence_figure"), "paper"),
}


def __getattr__(name: str):
    """``lungdeform.plot.<name>`` of ≤ 0.7 fails with one line naming its module now (an ImportError,
    so that ``from lungdeform.plot import <name>`` shows it too); other names are missing as usual.
    A module of the package that is imported is an attribute already, never asked here."""
    if name in MOVED and name != MOVED[name]:
        raise ImportError(f"lungdeform.plot.{name} moved to lungdeform.plot.{MOVED[name]}.{name} in 0.8 "
                          "(docs/CHANGELOG.md)")
    raise AttributeError(f"module 'lungdeform.plot' has no attribute {name!r}")
