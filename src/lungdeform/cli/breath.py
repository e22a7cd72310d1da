"""One breath for every command: the breathing options of ``warp``, ``dvf`` and ``track`` (docs/RADIOTHERAPY.md).

A command plays one named state (``--volume-ml``, ``--scan``) or the phases of one breath: ``--phases N``
states evenly over a cycle of ``--curve CSV``, of ``--preset NAME`` (``--cycles``, ``--tidal-ml``) or,
given neither, of the plain cycle (a 4 s cosine breath of ``--tidal-ml``, by default the tidal volume
the model was built for, else 500 mL); ``--phase K`` keeps phase K of those N. Phase 0 is end-inhale
unless ``--phase-zero`` says otherwise (:mod:`lungdeform.playback.phases`). The same options give the
same states in every command, so ``warp --phases``, ``dvf --phases`` and ``track --phases`` are one
breath phase for phase.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import typer

from lungdeform.breathing.presets import get_preset
from lungdeform.constants import TIDAL_VOLUME_ML
from lungdeform.errors import InputError
from lungdeform.playback import schedule as S
from lungdeform.playback.displacement_field import State, check_phases, phase_states
from lungdeform.playback.phases import PHASE_ZERO_HELP, check_zero, phase_schedule, scan_phase_text

from .common import check_cycles, check_tidal_ml, pick_state, read_curve, tidal_option, without_alignment

#: Where a refusal that needs a breath says one comes from.
BREATH_HINT = ("a breath: --curve CSV ('lungdeform breathe --out DIR' writes DIR/curve.csv), --preset NAME, or, "
               "given neither, the plain cycle")
PRESETS_HELP = "normal, deep, copd, restrictive, dyspnoea or pneumothorax"


@dataclass(frozen=True, kw_only=True)
class BreathFlags:
    """The breathing options of warp and dvf (an option group of :func:`lungdeform.cli.common.takes`)."""

    curve: Annotated[Path | None, typer.Option("--curve", help="Breathing curve CSV (t_s, volume_ml above end-exhale, …; 'lungdeform breathe' writes one); with --phases.")] = None
    preset: Annotated[str | None, typer.Option("--preset", help=f"Breathing preset of the PV model ({PRESETS_HELP}); with --phases.")] = None
    cycles: Annotated[int | None, typer.Option("--cycles", help="With --preset: whole breaths (default 1).")] = None
    tidal_ml: Annotated[float | None, typer.Option("--tidal-ml", callback=tidal_option, help="Tidal volume, both lungs (mL): of the plain cycle (default the model's own, else 500) or the --preset rescaled to it.")] = None
    phases: Annotated[int | None, typer.Option("--phases", help="This many states evenly over one breath of --curve, --preset or the plain cycle (phase 0 end-inhale).")] = None
    phase: Annotated[int | None, typer.Option("--phase", help="With --phases N: only phase K (0 to N-1) of them.")] = None
    phase_zero: Annotated[str, typer.Option("--phase-zero", help=PHASE_ZERO_HELP)] = "end-inhale"

    @property
    def inputs(self) -> list[Path | None]:
        """The files these options read, for :func:`lungdeform.cli.common.check_output`."""
        return [self.curve]


def check_breath(flags: BreathFlags, state_given: bool) -> None:
    """Refuse, before any work, breathing options that do not go together (``state_given``:
    ``--volume-ml`` or ``--scan``)."""
    if flags.phases is None:
        given = [name for name, v in (("--curve", flags.curve), ("--preset", flags.preset), ("--phase", flags.phase),
                                      ("--tidal-ml", flags.tidal_ml), ("--cycles", flags.cycles)) if v is not None]
        if given:
            raise InputError(f"{given[0]} goes with --phases N (how many states of the breath)")
        if not state_given:
            raise InputError(f"give --volume-ml, --scan or --phases N (states over {BREATH_HINT})")
        return
    if state_given:
        raise InputError("--phases with --volume-ml or --scan: give one breathing state or the phases of one breath")
    check_phases(flags.phases)
    if flags.phase is not None and not 0 <= flags.phase < flags.phases:
        raise InputError(f"--phase must be 0 to {flags.phases - 1} (a phase of --phases {flags.phases}), got {flags.phase}")
    check_zero(flags.phase_zero)
    check_trace_options(flags.curve, flags.preset, flags.cycles, flags.tidal_ml)


def check_trace_options(curve, preset, cycles, tidal_ml) -> None:
    """One breath at most (``--curve`` or ``--preset``), its options in range."""
    if curve is not None and preset is not None:
        raise InputError("--curve and --preset are mutually exclusive: give one breath")
    check_cycles(cycles, preset)
    check_tidal_ml(tidal_ml)
    if tidal_ml is not None and curve is not None:
        raise InputError("--tidal-ml applies to --preset or the plain cycle; a --curve has its own volumes")


def breath_trace(model, curve: Path | None, preset: str | None, cycles: int | None, tidal_ml: float | None):
    """The volume trace (:class:`lungdeform.playback.schedule.VolumeTrace`, mL above end-exhale) the
    options name: ``--curve``, ``--preset`` (``cycles`` breaths, rescaled to ``tidal_ml``) or the plain
    cycle of ``tidal_ml``, by default the tidal volume the model was built for (provenance
    ``tidal_ml``; 500 mL for a model without one, a fit)."""
    if curve is not None:
        return read_curve(curve, model)
    if preset is not None:
        _params, _curve, trace = S.preset_trace(get_preset(preset), cycles or 1, tidal_ml)
        return trace
    built = (model.provenance or {}).get("tidal_ml")
    return S.plain_cycle(float(tidal_ml or built or TIDAL_VOLUME_ML))


@dataclass(frozen=True)
class Breath:
    """The states a command plays: ``states`` (one :class:`~lungdeform.playback.displacement_field.State`
    per output); for phases ``indices`` (each state's phase index) and ``count`` (N), else None."""

    states: list[State]
    indices: list[int] | None = None
    count: int | None = None


def breath_states(model, flags: BreathFlags, named: tuple) -> Breath:
    """The states of the options: ``named`` = ``(--volume-ml, --scan, --no-rigid)`` for one state, or
    the phases of the breath (:func:`phase_states`), saying the cycle and which phase the scan is."""
    if flags.phases is None:
        volume_ml, scan, no_rigid = named
        return Breath([without_alignment(pick_state(model, volume_ml, scan), no_rigid)])
    trace = breath_trace(model, flags.curve, flags.preset, flags.cycles, flags.tidal_ml)
    states, period = phase_states(trace, flags.phases, flags.phase_zero)
    typer.echo(f"{len(states)} phase(s) over a cycle of {period:.2f} s of {trace.source} (phase 0 at {flags.phase_zero})")
    typer.echo(scan_phase_text(trace, phase_schedule(trace, flags.phases, flags.phase_zero), model.scan))
    indices = list(range(flags.phases)) if flags.phase is None else [flags.phase]
    return Breath([states[i] for i in indices], indices, flags.phases)
