"""Every figure the package draws: matplotlib's object-oriented API on the Agg canvas, one module per
kind of figure.

Each figure function builds and returns a :class:`matplotlib.figure.Figure` on its own canvas
(:func:`lungdeform.plot.figure.new_figure`); :func:`~lungdeform.plot.figure.save_png` writes one
atomically and :func:`~lungdeform.plot.figure.png_bytes` returns its bytes. No pyplot and no
``matplotlib.use``: nothing here keeps global state.

Owns:
- :mod:`~lungdeform.plot.figure`: a Figure on its own Agg canvas, PNG bytes and files;
- :mod:`~lungdeform.plot.surface`: lung surfaces by a small painter (:func:`snapshot`, :func:`error_map`);
- :mod:`~lungdeform.plot.fit`: the fit report's plots (error distributions, ray hits, bounding boxes,
  the direction field, the search's history);
- :mod:`~lungdeform.plot.segmentation`: the segmentation overlay on CT slices;
- :mod:`~lungdeform.plot.motion`: tracked points' displacement;
- :mod:`~lungdeform.plot.breathing`: breathing curves and their prediction;
- :mod:`~lungdeform.plot.statistics`: cohort and per-method statistics (box-and-strip, scatter, bars);
- :mod:`~lungdeform.plot.paper`: the paper's Figs. 7–9.

May import: :mod:`lungdeform.atomic` only (and numpy, matplotlib): every layer above may draw. The
package imports none of its modules: a caller imports the one it draws with, so only code that draws
imports matplotlib.
"""
