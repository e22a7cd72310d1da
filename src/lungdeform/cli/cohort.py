"""``lungdeform cohort MANIFEST.csv --out DIR``: fit every lung of a cohort on Dask, resumably.

The manifest (:mod:`lungdeform.cohort.manifest`) is checked in full before any work starts. Each lung is
fitted by :func:`lungdeform.cohort.job.fit_job` into ``DIR/subjects/<subject>/<side>/`` (written
atomically); a summary goes to ``DIR/cohort.json`` and population statistics next to it.

Exit status: 0 when at least one job succeeded (failed jobs are listed; their folders hold
``result.json`` and ``traceback.txt``), 1 when every job failed, 2 for a bad manifest or bad
options (one line naming the file and the rows), 130 when interrupted (Ctrl-C): what finished is
kept, and running the same command again resumes.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Optional

import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from lungdeform.cohort.job import STAGES, FitOptions
from lungdeform.cohort.manifest import read_manifest
from lungdeform.cohort.runner import Cluster, run_cohort

from .common import (
    DIRECTION_DEGREE_HELP,
    FIT_OPTIONS,
    SIDE_CHECK_HELP,
    option_names,
    output_dir,
    progress_enabled,
    takes,
)

#: Bar labels of the stages (lungdeform.cohort.job.STAGES).
STAGE_LABELS = {"read": "read / segment", "align": "align", "fit": "fit + measure", "write": "write"}
COHORT_OPTIONS = {"out": "--out", "workers": "--workers", "scheduler": "--scheduler"}
MAX_NOTES = 5


class Display:
    """Renders run_cohort's progress events: one rich bar per stage on stderr (live), or else one
    line per finished job on stdout. Keeps the tally the CLI reports at the end or on Ctrl-C."""

    def __init__(self, live: bool):
        self.live = live
        self.progress = None
        self.bars: dict[str, int] = {}
        self.reached: dict[str, int] = {}
        self.done: dict[str, dict] = {}
        self.skipped: dict[str, dict] = {}
        self.to_run = 0

    # -- events
    def __call__(self, ev: dict) -> None:
        kind = ev["event"]
        if kind == "start":
            self._start(ev)
        elif kind == "stage":
            self._advance(ev["job"], self._stages().index(ev["stage"]))
        elif kind == "done":
            if ev["skipped"]:
                self.skipped[ev["job"]] = ev["result"]
                return
            self._advance(ev["job"], len(self._stages()))
            self.done[ev["job"]] = ev["result"]
            self._line(_job_line(ev["result"]))
        elif kind == "population":
            self.stop()
            self._line(f"population statistics of {ev['ok']} fitted lung{'s' if ev['ok'] != 1 else ''} …")

    def _start(self, ev: dict) -> None:
        self.to_run = ev["to_run"]
        if ev["skipped"]:
            self._line(f"skipping {ev['skipped']} of {ev['jobs']} jobs already done (inputs and options unchanged)")
        if not ev["to_run"]:
            return
        where = (f"the Dask scheduler {ev['scheduler']}" if ev["scheduler"] != "local"
                 else f"a local Dask cluster of {ev['workers']} worker{'s' if ev['workers'] != 1 else ''}")
        self._line(f"fitting {ev['to_run']} job{'s' if ev['to_run'] != 1 else ''} on {where}")
        if self.live:
            self.progress = Progress(TextColumn("{task.description:<15}"), BarColumn(), MofNCompleteColumn(),
                                     TimeElapsedColumn(), console=Console(stderr=True), redirect_stdout=False,
                                     redirect_stderr=False)
            self.progress.start()
            for stage in self._stages():
                self.bars[stage] = self.progress.add_task(STAGE_LABELS.get(stage, stage), total=ev["to_run"])

    def _advance(self, job: str, upto: int) -> None:
        """The job has finished every stage before index ``upto``."""
        start = self.reached.get(job, 0)
        if upto <= start:
            return
        self.reached[job] = upto
        if self.progress is not None:
            for stage in self._stages()[start:upto]:
                self.progress.advance(self.bars[stage])

    def _line(self, text: str) -> None:
        if self.progress is not None:
            self.progress.console.print(text, highlight=False, markup=False, soft_wrap=True)
        else:
            typer.echo(text)

    @staticmethod
    def _stages():
        return STAGES

    def stop(self) -> None:
        if self.progress is not None:
            self.progress.stop()
            self.progress = None


def _job_line(r: dict) -> str:
    key = f"{r['subject']}/{r['side']}"
    if r["status"] == "ok":
        m = r["metrics"]
        lm = f", landmarks {m['landmark_mean_mm']:.2f} mm" if m.get("landmark_mean_mm") is not None else ""
        return (f"ok      {key:<24} {r['seconds']:7.1f} s  surface mean {m['surface_mean_mm']:.2f} mm, "
                f"objective {m['objective_rms_mm']:.2f} mm{lm}")
    return f"FAILED  {key:<24} {r['seconds']:7.1f} s  {r['error_type']}: {r['error']}"


@dataclass(frozen=True, kw_only=True)
class CohortOptions:
    """The options of ``lungdeform cohort`` (:func:`register`)."""

    manifest: Annotated[Path, typer.Argument(help="CSV: subject,side,volume_ml,path[,landmarks]; one row per scan.")]
    out: Annotated[Path, typer.Option("--out", help="Output folder: subjects/<subject>/<side>/, cohort.json, population statistics.")]
    scheduler: Annotated[Optional[str], typer.Option("--scheduler", help="Address of a running Dask scheduler (default: a local cluster).")] = None
    workers: Annotated[Optional[int], typer.Option("--workers", help="Worker processes of the local cluster (default: one per CPU, at most one per job).")] = None
    skip_failed: Annotated[bool, typer.Option("--skip-failed", help="Do not re-run jobs that failed in an earlier run.")] = False
    evaluations: Annotated[int, typer.Option("--evaluations", help="Optimiser budget per fit (objective evaluations).")] = 300
    baselines: Annotated[bool, typer.Option("--baselines/--no-baselines", help="Measure the baselines too.")] = True
    processes: Annotated[bool, typer.Option("--processes/--threads", help="Local workers as processes, or threads in this process (debugging).")] = True
    align: Annotated[str, typer.Option("--align", help="apex: rigid alignment on the apex cap (scans with a table shift); "
        "joint: a translation per target fitted with the constants; none: inputs already in one "
        "frame (a synthetic cohort from synth-cohort: use none or joint).")] = "apex"
    landmark_fit: Annotated[bool, typer.Option("--landmark-fit/--no-landmark-fit", help="With landmarks: the interior landmark correction, k-fold cross-validated.")] = True
    folds: Annotated[int, typer.Option("--folds", help="Folds of the landmark cross-validation.")] = 5
    direction_degree: Annotated[int, typer.Option("--direction-degree", help=DIRECTION_DEGREE_HELP)] = 3
    stiffness: Annotated[bool, typer.Option("--stiffness/--no-stiffness", help="Also fit a heterogeneous stiffness field per lung (kept only if it lowers the objective; slower).")] = False
    side_check: Annotated[bool, typer.Option("--side-check/--no-side-check", help=SIDE_CHECK_HELP)] = True


def register(apps) -> None:
    @apps.root.command("cohort")
    @takes(CohortOptions)
    def cohort_command(opts: CohortOptions) -> None:
        """Fit every lung of a cohort in parallel on Dask; resumable (finished subjects are skipped).

        Exit 0 if at least one job succeeded (failures listed), 1 if all failed, 2 for a bad
        manifest, 130 when interrupted (re-run the same command to resume)."""

        m = read_manifest(opts.manifest)  # every problem reported before any work starts (exit 2)
        with option_names(FIT_OPTIONS):
            options = FitOptions(max_evaluations=opts.evaluations, baselines=opts.baselines, align=opts.align,
                                 landmark_fit=opts.landmark_fit, folds=opts.folds,
                                 direction_degree=opts.direction_degree, stiffness=opts.stiffness, side_check=opts.side_check)
        if opts.align == "apex" and (Path(opts.manifest).parent / "truth.json").is_file():
            typer.echo("note: this manifest's folder holds a synthetic truth.json: its surfaces are already in one "
                       "frame, and the apex alignment shifts them (the model moves the apex); use --align none "
                       "(or joint) to measure recovery")
        for note in m.notes[:MAX_NOTES]:
            typer.echo(f"note: {note}")
        if len(m.notes) > MAX_NOTES:
            typer.echo(f"note: … and {len(m.notes) - MAX_NOTES} more such notes (all in cohort.json)")
        folder = output_dir(opts.out)
        display = Display(progress_enabled())
        try:
            with option_names(COHORT_OPTIONS):
                cluster = Cluster(scheduler=opts.scheduler, workers=opts.workers, processes=opts.processes)
                result = run_cohort(m, folder, cluster=cluster, options=options, skip_failed=opts.skip_failed,
                                    progress=display)
        except KeyboardInterrupt:
            display.stop()
            typer.echo(f"interrupted: {_tally(folder, display)}; results are in {folder / 'subjects'}, summary in "
                       f"{folder / 'cohort.json'}. Run the same command again to resume: finished jobs are skipped.",
                       err=True)
            raise typer.Exit(130) from None
        finally:
            display.stop()
        _report(result, folder)
        if not result.ok:
            first = result.failed[0]
            typer.echo(f"error: all {len(result.results)} jobs failed (first: {first['subject']}/{first['side']}: "
                       f"{first['error_type']}: {first['error']})", err=True)
            raise typer.Exit(1)


def _tally(folder: Path, display: Display) -> str:
    """What finished, from the cohort.json written on the interrupt (it also counts jobs that
    finished on a worker after this process stopped listening), else from the events seen."""

    try:
        jobs = json.loads((folder / "cohort.json").read_text(encoding="utf-8"))["jobs"]
        return (f"{jobs['ok'] + jobs['failed']} of {jobs['total']} jobs done ({jobs['ok']} ok, {jobs['failed']} "
                f"failed, {jobs['skipped']} of them done before), {jobs['not_run']} not run")
    except (OSError, ValueError, KeyError, TypeError):
        ok = sum(r["status"] == "ok" for r in display.done.values())
        return (f"{len(display.done)} of {display.to_run} jobs finished in this run ({ok} ok, "
                f"{len(display.done) - ok} failed)")


def _report(result, folder: Path) -> None:
    n, ok, failed = len(result.results), len(result.ok), result.failed
    typer.echo(f"cohort: {n} job{'s' if n != 1 else ''}: {ok} ok, {len(failed)} failed, "
               f"{len(result.skipped)} skipped as already done ({result.seconds:.1f} s)")
    if failed:
        typer.echo("failed jobs (their folders hold result.json and traceback.txt; re-run to retry):")
        for r in failed:
            typer.echo(f"  {r['subject']}/{r['side']}: {r['error_type']}: {r['error']}")
    typer.echo(f"wrote {folder / 'cohort.json'} and {folder / 'subjects'}/<subject>/<side>/")
    if result.population:
        for line in _population_lines(result.population):
            typer.echo(line)
        files = result.population.get("files") or {}
        if files:
            typer.echo(f"population statistics in {folder}: {', '.join(sorted(_relative(p, folder) for p in files.values()))}")


def _g(v) -> str:
    return "-" if v is None else f"{v:.3g}"


def _population_lines(pop: dict) -> list[str]:
    """The Table I comparison per side (mean ± SD [min, max] against the paper, flagged when outside
    the range) and the time per lung, from write_population's summary (parts missing: not printed)."""
    lines = []
    for side, rows in (pop.get("table_i") or {}).items():
        lines.append(f"{side}: c1…c9, mean ± SD [min, max] over the lungs against Table I (c7…c9 normalised):")
        for c, v in rows.items():
            flag = {True: "", False: "  outside the range", None: ""}[v["in_range"]]
            lines.append(f"  {c}  {_g(v['mean']):>8} ± {_g(v['sd']):<8} [{_g(v['min'])}, {_g(v['max'])}]  "
                         f"paper {_g(v['paper'])}  n={v['n']}{flag}")
    t = pop.get("time_per_lung") or {}
    if t.get("n"):
        lines.append(f"time per lung: median {t['median_s']:.1f} s (min {t['min_s']:.1f}, max {t['max_s']:.1f}; "
                     f"{t['n']} lung{'s' if t['n'] != 1 else ''}, {t['total_s']:.0f} s in all)")
    return lines


def _relative(path, folder: Path) -> str:
    try:
        return str(Path(path).resolve().relative_to(folder.resolve()))
    except ValueError:
        return str(path)
