"""Tune the CPD surface baseline's kernel width β and outlier weight w, leave one subject out.

Why (issue 39): the model's settings were chosen on the data it is scored on, so the non-physical
registration it is compared with gets a search of its own. The baseline is
:func:`lungdeform.evaluate.baselines.cpd_deformable` after its own translation, exactly as
``lungdeform validate copd`` runs it (:func:`lungdeform.evaluate.scoring.baseline_methods`); each
setting is scored by the mean held-out landmark error (the landmarks never enter CPD; they move by
the sliding interpolation every method shares), and the surface distance is recorded beside it.
Leave one subject out: for each case, the setting with the lowest median landmark error over the
*other* cases' lungs, scored on that case's two lungs.

Usage (from the repository root; a few minutes per lung on a quiet machine, resumable: each lung's
figures are kept in ``--out`` as they are computed)::

    LUNGDEFORM_DATA=/work/shared/data .venv/bin/python scripts/tune_cpd_baseline.py \\
        --data $LUNGDEFORM_DATA/dirlab-copd-lung-masks --out cpd_search.json [--cases 1,2,3,4,5]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from lungdeform.atomic import write_json
from lungdeform.evaluate import baselines as B
from lungdeform.evaluate.inputs import read_inputs
from lungdeform.evaluate.placement import place_targets
from lungdeform.fit.config import FitInputs
from lungdeform.segment.split import SIDES, SplitCache
from lungdeform.validate.copd import find_cases

#: The grid: β relative to the lung's RMS radius (pycpd's usual 2; 0.2–1 slid tangentially on the ITK
#: pair), w the outlier weight (pycpd's usual 0.05). A first run on β ∈ {1, 2, 4} × w ∈ {0, 0.05, 0.2}
#: picked β 4, the grid's edge, with w changing the median by at most 0.01 mm; so the grid goes on
#: upwards with the two smaller w.
BETAS = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)
WS = (0.0, 0.05)
#: The CPD settings the search overrides (the rest must equal the baseline's for a lung's figures to be reused).
SEARCHED = ("beta", "w")


def setting_name(beta: float, w: float) -> str:
    """The key of one setting in the search's tables, e.g. ``"4,0.05"``."""
    return f"{beta:g},{w:g}"


def lung_scores(files, side: str, splits: SplitCache, done: dict | None = None) -> dict:
    """``{"beta,w": {"landmark_mean_mm", "surface_mean_mm"}}`` of one lung for every setting of the
    grid; the settings already in ``done`` (the same table, read back) are kept, not run again."""
    exp_mask, insp_mask, exp_lm, insp_lm = files
    inputs = FitInputs([exp_mask, insp_mask], side, landmarks=[exp_lm, insp_lm], splits=splits)
    read = read_inputs(inputs)
    placed = place_targets(read, read.paths, inputs.landmarks, "apex")
    rest, target, keep = placed.rest, placed.targets[-1], placed.keep
    pairs = B.LandmarkPairs(read.landmarks[0], placed.landmarks[-1], B.landmark_matrix(rest, read.landmarks[0], keep))
    shift = B.best_translation(rest, target.surface, keep=keep, keep_target=target.keep)
    shifted = rest.deformed(np.broadcast_to(shift, rest.vertices.shape))
    out = {}
    for beta, w in itertools.product(BETAS, WS):
        if setting_name(beta, w) in (done or {}):
            out[setting_name(beta, w)] = done[setting_name(beta, w)]
            continue
        x = B.cpd_deformable(shifted, target.surface, replace(B.CpdSettings(), beta=beta, w=w), keep=keep,
                             keep_target=target.keep)
        m, _, _ = B.measure(rest, x, target.surface, keep=keep, keep_target=target.keep, landmarks=pairs)
        out[setting_name(beta, w)] = {"landmark_mean_mm": m.landmark_mean_mm, "surface_mean_mm": m.surface_mean_mm}
    return out


def reusable(doc: dict, grid: dict) -> dict:
    """The per-lung figures of an earlier search (``doc``, the script's output read back) that this
    grid can keep: those of its settings, when every CPD setting but the searched ones is the same."""
    def fixed(g):
        return {k: v for k, v in g.get("cpd", {}).items() if k not in SEARCHED}

    if "grid" not in doc or fixed(doc["grid"]) != fixed(grid):
        return {}
    names = {setting_name(b, w) for b, w in itertools.product(BETAS, WS)}
    return {lung: {s: v for s, v in row.items() if s in names} for lung, row in doc.get("lungs", {}).items()}


def leave_one_subject_out(lungs: dict) -> dict:
    """Per case, the setting best (median landmark error) on the other cases' lungs, and its figures
    on that case's lungs; ``lungs``: ``{"copdN/side": lung_scores(...)}``."""
    cases = sorted({k.split("/")[0] for k in lungs})
    settings = list(next(iter(lungs.values())))
    out = {}
    for case in cases:
        others = [k for k in lungs if not k.startswith(case + "/")]
        pick = min(settings, key=lambda s: np.median([lungs[k][s]["landmark_mean_mm"] for k in others]))
        out[case] = {"setting": pick, **{k: lungs[k][pick] for k in lungs if k.startswith(case + "/")}}
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, required=True)
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--cases", default=None, help="comma-separated case numbers (default: all)")
    args = ap.parse_args(argv)
    doc = json.loads(args.out.read_text()) if args.out.is_file() else {}
    grid = {"betas": list(BETAS), "ws": list(WS), "cpd": asdict(B.CpdSettings())}
    lungs = reusable(doc, grid)
    cases = None if args.cases is None else [int(c) for c in args.cases.split(",")]
    for name, files in find_cases(args.data, cases).items():
        splits = SplitCache()
        for side in SIDES:
            key = f"{name}/{side}"
            todo = len(BETAS) * len(WS) - len(lungs.get(key, {}))
            if todo == 0:
                continue
            print(f"{key}: {todo} CPD runs", file=sys.stderr, flush=True)
            lungs[key] = lung_scores(files, side, splits, lungs.get(key))
            write_json(args.out, {"grid": grid, "lungs": lungs}, indent=1)  # atomic: a killed run keeps the last lung
    default = setting_name(B.CpdSettings().beta, B.CpdSettings().w)
    med = {s: float(np.median([r[s]["landmark_mean_mm"] for r in lungs.values()])) for s in next(iter(lungs.values()))}
    print(f"{len(lungs)} lungs; median landmark error (mm) by beta,w: "
          + ", ".join(f"{s}: {v:.2f}" for s, v in sorted(med.items(), key=lambda kv: kv[1])))
    loso = leave_one_subject_out(lungs) if len({k.split('/')[0] for k in lungs}) > 1 else {}
    held = [v["landmark_mean_mm"] for c in loso.values() for k, v in c.items() if k != "setting"]
    if held:
        print(f"leave one subject out: median {np.median(held):.2f} mm (default {default}: {med[default]:.2f}); "
              f"settings picked: {sorted({c['setting'] for c in loso.values()})}")
    write_json(args.out, {"grid": grid, "lungs": lungs, "median_by_setting": med, "leave_one_subject_out": loso},
               indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
