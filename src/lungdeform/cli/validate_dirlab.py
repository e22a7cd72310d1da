"""``lungdeform validate dirlab``: test the paper's motion hypotheses on DIR-Lab 4-D CT landmarks."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from lungdeform.atomic import write_bytes
from lungdeform.errors import InputError
from lungdeform.validate import dirlab as D

from .common import output_dir


def register(apps) -> None:
    @apps.validate.command("dirlab")
    def dirlab_command(
        data: Path = typer.Option(..., "--data", help="DIR-Lab folder: the one holding the case folders, a folder above it, or one case folder "
                                       "(cases are found by file name)."),
        out: Path = typer.Option(..., "--out", help="Output folder; metrics.json is written there."),
        folds: int = typer.Option(5, "--folds", help="Landmark folds for fitting held-out drivers."),
        published_spacing: bool = typer.Option(
            True, "--published-spacing/--no-published-spacing",
            help="For a case 1–10 that voxel_spacing.csv does not list (or with no table at all), use DIR-Lab's "
                 "published spacing, with a note; --no-published-spacing makes it an error.",
        ),
    ) -> None:
        """Predict T10–T40 landmarks from T00/T50 with one scalar per phase, and richer real-time models."""


        if folds < 2:
            raise InputError(f"--folds must be ≥ 2, got {folds}")
        t0 = time.perf_counter()
        found = D.discover(data, published_fallback=published_spacing)
        cases = found.cases
        results = [D.evaluate_case(D.load_case(f), f.dims, folds=folds) for f in cases.values()]
        summary = D.hypothesis_summary(results)
        elapsed = time.perf_counter() - t0

        names = list(D.MODELS)
        short = {m: m.replace("_landmark", "_lm").replace("_region", "_rg").replace("two_component", "two_comp") for m in names}
        typer.echo("DIR-Lab, mean errors in mm over T10–T40 (75 landmarks). T00 = end-inhale, T50 = end-exhale:")
        typer.echo("T10–T40 are exhale phases; the held-out columns leave one phase out.")
        head = f"{'case':>4} {'300 mean':>8} {'publ.':>6} {'none':>6} {'1 scal':>6} {'floor':>6} | " + " ".join(
            f"{short[m]:>9}" for m in names
        ) + " | best"
        typer.echo(head)
        for r in results:
            disp = "-" if r.mean_displacement_300_mm is None else f"{r.mean_displacement_300_mm:.2f}"
            pub = "-" if r.published_300_mm is None else f"{r.published_300_mm:.2f}"
            if r.best_model is None:
                typer.echo(f"{r.case:>4} {disp:>8} {pub:>6}   (no 75-point phase files: motion models skipped)")
                continue
            typer.echo(
                f"{r.case:>4} {disp:>8} {pub:>6} {r.no_motion_mean_mm:>6.2f} {r.one_scalar_mean_mm:>6.2f} "
                f"{r.rounding_floor_mm:>6.2f} | "
                + " ".join(f"{r.heldout_mean_mm[m]:>9.3f}" for m in names)
                + f" | {r.best_model} ({r.best_model_heldout_mean_mm:.3f})"
            )
        for case, why in sorted(found.skipped.items()):
            typer.echo(f"{case:>4}   (skipped: {why.split(': skipped: ', 1)[-1]})")
        notes = list(found.notes) + [n for f in cases.values() for n in f.notes] + list(found.skipped.values())
        for r in results:
            if r.mean_displacement_300_mm is not None and r.published_300_mm is not None and \
                    abs(r.mean_displacement_300_mm - r.published_300_mm) > 0.05:
                src = cases[r.case].spacing_source
                check = "check its landmark files" if src == D.PUBLISHED_SOURCE else f"check its row in {src}"
                notes.append(f"case {r.case}: 300-pair mean {r.mean_displacement_300_mm:.2f} mm differs from the "
                             f"published {r.published_300_mm:.2f} mm: {check}")
        for n in notes:
            typer.echo(f"note: {n}")
        typer.echo(f"magnitude set by one scalar per phase: {summary['magnitude_one_scalar']}")
        typer.echo(f"direction constant: {summary['direction_constant']}")

        metrics = {
            "cases": {
                str(r.case): {**r.to_dict(), "spacing_mm": cases[r.case].spacing.tolist(),
                              "spacing_source": cases[r.case].spacing_source}
                for r in results
            },
            "skipped": {str(c): why for c, why in sorted(found.skipped.items())},
            "hypotheses": summary,
            "notes": notes,
            "conventions": {
                "frame": "mm = (1-based voxel index - 1) * spacing (voxel_spacing.csv), index-aligned, not LPS",
                "phases": "T00 end-inhale, T50 end-exhale; T10-T40 on the exhale branch (no inhale samples)",
                "one_scalar": "x_p = x_T50 + s_p (x_T00 - x_T50), s_p least squares per phase, in-sample",
                "heldout": f"leave one of T10-T40 out; drivers fitted on other landmark folds ({folds})",
                "rounding_floor": "mean error of a perfect model given whole-voxel landmark positions",
            },
            "source": str(Path(data).resolve()),
            "elapsed_s": elapsed,
        }
        path = output_dir(out) / "metrics.json"
        write_bytes(path, (json.dumps(metrics, indent=2) + "\n").encode())
        typer.echo(f"wrote {path} ({len(results)} case(s), {elapsed:.2f} s)")

