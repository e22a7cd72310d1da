"""Breathing driver: the pressure–volume (PV) relation of the paper (Sec. III-A/B).

The reading we implement ("a standard reading") is the single-compartment equation of
motion of the respiratory system,

    I·V''(t) + R·V'(t) + E·(V(t) − V_r) = P_mus(t),        P_mus(t) = Σ_{k=1..5} a_k·φ_k(θ(t)),

with ``V`` lung volume (L internally, mL at the outputs), ``V_r`` the relaxation volume (FRC of the
passive system), ``E`` elastance (cmH2O/L), ``R`` resistance (cmH2O·s/L), ``I`` inertance
(cmH2O·s²/L), and ``P_mus`` the muscle pressure (cmH2O), the paper's "control function": a linear sum
of five control parameters ``a_k`` (cmH2O) times basis functions ``φ_k`` of the breathing phase
``θ ∈ [0, 1)`` (0 = start of inspiration = end-exhale, 1 = next end-exhale).

Basis functions (the choice, and why)
-------------------------------------
The paper's own basis (Santhanam 2006 thesis, its ref. [45]) is not published in the text we hold, so
we use the classic description of the respiratory muscle pressure waveform (Younes & Riddle,
J Appl Physiol 1984;56:1-13 "Relation between respiratory neural output and tidal volume";
Riddle & Younes 1981): inspiratory pressure rises as a low-order polynomial of inspiratory time, is
followed by post-inspiratory inspiratory activity (PIIA) that decays within the first part of
expiration, expiration is otherwise passive unless expiratory muscles are recruited (exercise,
COPD, forced manoeuvres). With the inspiratory fraction ρ = T_i/T_tot, u = θ/ρ in inspiration and
w = (θ − ρ)/(1 − ρ) in expiration, and g(w) = (1 − w)·exp(−w/κ) the PIIA decay (κ = decay constant as
a fraction of T_e; g(1) = 0 so every φ_k is continuous and periodic):

  ===  ======================  =======================  ============================================
  k    inspiration (u)         expiration (w)           physiology
  ===  ======================  =======================  ============================================
  1    1                       1                        tonic activity: shifts end-expiratory volume
  2    u                       g(w)                     linear inspiratory drive + PIIA decay
  3    u²                      g(w)                     quadratic (accelerating) drive (Younes-Riddle)
  4    0                       sin²(πw)                 expiratory-muscle activity (a_4 < 0 pushes)
  5    sin²(πu)                0                        mid-inspiratory drive shape (bulge/plateau)
  ===  ======================  =======================  ============================================

The inversion of this relation from a measured volume trace (the a_k and the shape constants τ,
I/E, ρ, κ) is :mod:`lungdeform.breathing.inversion`.

Two solvers, one equation:

- :func:`periodic_response`: the exact periodic steady state for a cycle of duration T, by Fourier
  series: V̂(ω) = P̂(ω)/(E + iωR − ω²I). Used by the fit (:mod:`lungdeform.breathing.inversion`; fast, no
  transients).
- :func:`simulate`: forward integration of the second-order ODE with scipy's implicit Radau method
  (A-stable; the inertial mode R/I ≈ 300 1/s makes the system stiff), cycle by cycle, any number of
  cycles, any per-cycle durations, from the periodic state or from rest (shows air trapping).

Units: parameters in cmH2O, L, L/s, s; the outputs of :class:`BreathingCurve` in mL, mL/s, cmH2O.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
from scipy.integrate import solve_ivp

from lungdeform.errors import ConvergenceError, InputError

N_CONTROL = 5
#: Phase samples per cycle used by :func:`periodic_response` (Fourier grid).
N_PHASE = 1024


# --------------------------------------------------------------------------- parameters
@dataclass(frozen=True)
class Mechanics:
    """Respiratory mechanics of the single compartment.

    elastance : float, cmH2O/L (E_rs); resistance : float, cmH2O·s/L (R_rs);
    inertance : float, cmH2O·s²/L (I_rs, ≈ 0.01 in adults; 0 gives the first-order model).
    """

    elastance: float
    resistance: float
    inertance: float = 0.01

    def __post_init__(self):
        for name in ("elastance", "resistance", "inertance"):
            value = getattr(self, name)
            if not np.isfinite(value) or value < 0 or (name != "inertance" and value <= 0):
                raise InputError(f"Mechanics.{name} must be a finite positive number, got {value!r}")

    @property
    def time_constant_s(self) -> float:
        """τ = R/E, s: the passive expiratory time constant."""
        return self.resistance / self.elastance


@dataclass(frozen=True)
class BreathingParams:
    """Everything the PV relation needs to breathe.

    mechanics : :class:`Mechanics`; control : (5,) float, cmH2O (a_1..a_5);
    period_s : float, s (T_tot); insp_fraction : float (ρ = T_i/T_tot of the muscle drive);
    decay : float (κ, PIIA decay constant as a fraction of T_e); relaxation_ml : float, mL (V_r).
    """

    mechanics: Mechanics
    control: tuple
    period_s: float = 4.0
    insp_fraction: float = 0.4
    decay: float = 0.15
    relaxation_ml: float = 2400.0

    def __post_init__(self):
        a = np.asarray(self.control, dtype=float)
        if a.shape != (N_CONTROL,) or not np.all(np.isfinite(a)):
            raise InputError(f"control must be 5 finite numbers (a_1..a_5, cmH2O), got {self.control!r}")
        object.__setattr__(self, "control", tuple(float(x) for x in a))
        if not (np.isfinite(self.period_s) and self.period_s > 0):
            raise InputError(f"period_s must be > 0 s, got {self.period_s!r}")
        if not (0.05 <= self.insp_fraction <= 0.95):
            raise InputError(f"insp_fraction must lie in [0.05, 0.95], got {self.insp_fraction!r}")
        if not (0.005 <= self.decay <= 5.0):
            raise InputError(f"decay must lie in [0.005, 5] (fraction of expiration), got {self.decay!r}")

    @property
    def a(self) -> np.ndarray:
        """(5,) float, cmH2O: the control parameters."""
        return np.asarray(self.control, dtype=float)

    def as_dict(self) -> dict:
        m = self.mechanics
        return {
            "elastance_cmH2O_per_L": m.elastance,
            "resistance_cmH2O_s_per_L": m.resistance,
            "inertance_cmH2O_s2_per_L": m.inertance,
            "time_constant_s": m.time_constant_s,
            "control_cmH2O": list(self.control),
            "period_s": self.period_s,
            "insp_fraction": self.insp_fraction,
            "decay": self.decay,
            "relaxation_ml": self.relaxation_ml,
        }


# --------------------------------------------------------------------------- basis
def basis(theta, insp_fraction: float, decay: float) -> np.ndarray:
    """The five control basis functions at phases ``theta``.

    theta : (n,) float, cycle phase (wrapped into [0, 1)). Returns (n, 5) float, dimensionless.
    """
    th = np.mod(np.asarray(theta, dtype=float), 1.0)
    rho = float(insp_fraction)
    insp = th < rho
    u = np.where(insp, th / rho, 0.0)
    w = np.where(insp, 0.0, (th - rho) / (1.0 - rho))
    g = (1.0 - w) * np.exp(-w / decay)
    out = np.empty(th.shape + (N_CONTROL,))
    out[..., 0] = 1.0
    out[..., 1] = np.where(insp, u, g)
    out[..., 2] = np.where(insp, u * u, g)
    out[..., 3] = np.where(insp, 0.0, np.sin(np.pi * w) ** 2)
    out[..., 4] = np.where(insp, np.sin(np.pi * u) ** 2, 0.0)
    return out


def muscle_pressure(theta, params: BreathingParams) -> np.ndarray:
    """P_mus at phases ``theta`` (n,) -> (n,) float, cmH2O."""
    return basis(theta, params.insp_fraction, params.decay) @ params.a


def transfer(omega, mechanics: Mechanics) -> np.ndarray:
    """H(ω) = E + iωR − ω²I, cmH2O/L: pressure per volume at angular frequency ω (rad/s)."""
    w = np.asarray(omega, dtype=float)
    return mechanics.elastance + 1j * w * mechanics.resistance - w * w * mechanics.inertance


def periodic_response(period_s: float, mechanics: Mechanics, insp_fraction: float, decay: float,
                      n_phase: int = N_PHASE) -> tuple[np.ndarray, np.ndarray]:
    """Periodic steady-state response to each basis function, on a uniform phase grid.

    Returns ``(volume, flow)``, each (n_phase, 5) float: volume in L per cmH2O of a_k and flow in
    L/s per cmH2O, at phases θ_j = j/n_phase. Exact for the Fourier series truncated at n_phase/2.
    """
    theta = np.arange(n_phase) / n_phase
    phi = basis(theta, insp_fraction, decay)
    spec = np.fft.rfft(phi, axis=0)
    omega = 2.0 * np.pi * np.arange(spec.shape[0]) / period_s
    h = transfer(omega, mechanics)
    vspec = spec / h[:, None]
    volume = np.fft.irfft(vspec, n=n_phase, axis=0)
    flow = np.fft.irfft(vspec * (1j * omega)[:, None], n=n_phase, axis=0)
    return volume, flow


def interp_periodic(grid_values: np.ndarray, theta) -> np.ndarray:
    """Linear interpolation of (m, ...) values on the phase grid j/m at phases ``theta`` (n,)."""
    m = grid_values.shape[0]
    x = np.mod(np.asarray(theta, dtype=float), 1.0) * m
    i0 = np.floor(x).astype(int) % m
    frac = (x - np.floor(x))
    i1 = (i0 + 1) % m
    if grid_values.ndim == 2:
        frac = frac[:, None]
    return grid_values[i0] * (1.0 - frac) + grid_values[i1] * frac


# --------------------------------------------------------------------------- curve
def scale_from_volume(volume_ml, v_ee_ml: float, unit_ml: float):
    """Playback scale s = (V − V_EE)/ΔV (paper eq. (1), Sec. V): the surface is x = p + s·u.

    volume_ml : float or (n,) float, mL; v_ee_ml : end-exhale volume, mL; unit_ml : ΔV, mL per unit
    displacement field u. Returns s with the shape of ``volume_ml``.
    """
    if not (np.isfinite(unit_ml) and unit_ml != 0):
        raise InputError(f"unit_ml must be a finite non-zero volume in mL, got {unit_ml!r}")
    return (np.asarray(volume_ml, dtype=float) - float(v_ee_ml)) / float(unit_ml)


@dataclass(frozen=True)
class BreathingCurve:
    """A breathing curve sampled in time (what curve.csv holds).

    t_s : (n,) float, s, increasing; volume_ml : (n,) float, mL (absolute lung volume);
    flow_ml_s : (n,) float, mL/s (inspiration > 0); pressure_cmH2O : (n,) float, cmH2O (P_mus).
    """

    t_s: np.ndarray
    volume_ml: np.ndarray
    flow_ml_s: np.ndarray
    pressure_cmH2O: np.ndarray
    meta: dict = field(default_factory=dict, compare=False)

    def __post_init__(self):
        n = None
        for name in ("t_s", "volume_ml", "flow_ml_s", "pressure_cmH2O"):
            arr = np.ascontiguousarray(getattr(self, name), dtype=float)
            if arr.ndim != 1 or (n is not None and arr.shape[0] != n):
                raise InputError(f"BreathingCurve.{name} must be (n,) like t_s, got {arr.shape}")
            n = arr.shape[0]
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        if n < 2 or np.any(np.diff(self.t_s) <= 0):
            raise InputError("BreathingCurve.t_s must hold at least 2 strictly increasing times")

    @property
    def v_ee_ml(self) -> float:
        """End-exhale volume, mL: the minimum of the curve."""
        return float(self.volume_ml.min())

    @property
    def tidal_volume_ml(self) -> float:
        return float(self.volume_ml.max() - self.volume_ml.min())

    def volume_at(self, t_s):
        """Volume (mL) at times ``t_s`` (float or (n,)), linear interpolation, clamped at the ends."""
        return np.interp(t_s, self.t_s, self.volume_ml)

    def scale_at(self, t_s, unit_ml: float, v_ee_ml: float | None = None):
        """Playback scale s(t) = (V(t) − V_EE)/ΔV for the core's x = p + s·u."""
        v_ee = self.v_ee_ml if v_ee_ml is None else v_ee_ml
        return scale_from_volume(self.volume_at(t_s), v_ee, unit_ml)


# --------------------------------------------------------------------------- forward simulation
def _cycle_starts(n_cycles: int | None, period_s: float, durations_s) -> np.ndarray:
    if durations_s is None:
        if n_cycles is None or int(n_cycles) < 1:
            raise InputError(f"n_cycles must be >= 1, got {n_cycles!r}")
        durations = np.full(int(n_cycles), float(period_s))
    else:
        durations = np.asarray(durations_s, dtype=float).ravel()
        if durations.size < 1 or np.any(~np.isfinite(durations)) or np.any(durations <= 0):
            raise InputError("durations_s must be positive cycle durations in s")
    return np.concatenate([[0.0], np.cumsum(durations)])


def _output_grid(starts: np.ndarray, fs_hz: float) -> np.ndarray:
    """Output times (s): ``k/fs_hz`` up to the end of the last cycle, the last one clamped to it."""
    t_out = np.arange(0.0, starts[-1] + 0.5 / fs_hz, 1.0 / fs_hz)
    t_out = t_out[t_out <= starts[-1] + 1e-9]
    t_out[-1] = min(t_out[-1], starts[-1])
    return t_out


def _cycle_ode(params: BreathingParams, t0: float, ti: float, te: float):
    """``(pmus, rhs, jac)`` of one cycle starting at ``t0`` with inspiration ``ti`` and expiration
    ``te`` (s): P_mus(t) (cmH2O), the right-hand side of the state ``(V L, V' L/s)`` and its Jacobian."""
    mech = params.mechanics
    e, r, inert = mech.elastance, mech.resistance, mech.inertance
    a1, a2, a3, a4, a5 = (float(x) for x in params.a)
    kappa = params.decay

    def pmus(t):
        # scalar P_mus, the same formulas as basis() (kept scalar for the integrator's speed)
        x = t - t0
        if x < ti:
            u = x / ti
            return a1 + a2 * u + a3 * u * u + a5 * math.sin(math.pi * u) ** 2
        w = min((x - ti) / te, 1.0)
        g = (1.0 - w) * math.exp(-w / kappa)
        return a1 + (a2 + a3) * g + a4 * math.sin(math.pi * w) ** 2

    if inert > 0:
        jac = np.array([[0.0, 1.0], [-e / inert, -r / inert]])

        def rhs(t, y):
            return [y[1], (pmus(t) - e * y[0] - r * y[1]) / inert]
    else:
        jac = np.array([[-e / r, 0.0], [0.0, 0.0]])

        def rhs(t, y):
            return [(pmus(t) - e * y[0]) / r, 0.0]
    return pmus, rhs, jac


def _integrate_cycle(params: BreathingParams, starts: np.ndarray, c: int, y0, t_out, out, rtol: float,
                     atol: float) -> np.ndarray:
    """Integrate cycle ``c`` from state ``y0`` in two pieces (inspiration, expiration), so the
    implicit solver never steps over a kink of P_mus; fills ``out = (v, f, p)`` at the output times
    ``t_out`` inside the cycle (the very last one included) and returns the end state."""
    t0, t1 = starts[c], starts[c + 1]
    dur = t1 - t0
    ti = params.insp_fraction * dur
    pmus, rhs, jac = _cycle_ode(params, t0, ti, dur - ti)
    v_out, f_out, p_out = out
    for s0, s1 in ((t0, t0 + ti), (t0 + ti, t1)):
        last = c == starts.size - 2 and s1 == t1
        sel = (t_out >= s0) & ((t_out <= s1) if last else (t_out < s1))
        t_eval = np.unique(np.concatenate([t_out[sel], [s1]]))
        sol = solve_ivp(rhs, (s0, s1), y0, method="Radau", t_eval=t_eval, rtol=rtol, atol=atol,
                        jac=jac, max_step=dur / 20.0)
        if not sol.success:
            raise ConvergenceError(f"breathing ODE integration failed in cycle {c}: {sol.message}")
        keep = np.isin(sol.t, t_out[sel])
        v_out[sel] = sol.y[0][keep]
        f_out[sel] = sol.y[1][keep]
        p_out[sel] = [pmus(tt) for tt in sol.t[keep]]
        y0 = sol.y[:, -1].copy()
    return y0


def simulate(params: BreathingParams, n_cycles: int | None = 3, fs_hz: float = 50.0,
             durations_s=None, start: str = "periodic", rtol: float = 1e-7,
             atol: float = 1e-10) -> BreathingCurve:
    """Integrate the equation of motion over whole cycles (scipy ``solve_ivp``, Radau).

    n_cycles : cycles of ``params.period_s`` (ignored when ``durations_s`` (k,) s is given);
    fs_hz : output sample rate; start : "periodic" (steady state of the first cycle) or "rest"
    (V = V_r, V' = 0: transients such as dynamic hyperinflation show). Integration restarts at each
    kink of P_mus (start and end of inspiration) so the implicit solver never steps over one.
    Raises ConvergenceError if the integrator fails.
    """

    if not (np.isfinite(fs_hz) and fs_hz > 0):
        raise InputError(f"fs_hz must be > 0, got {fs_hz!r}")
    if start not in ("periodic", "rest"):
        raise InputError(f"start must be 'periodic' or 'rest', got {start!r}")
    starts = _cycle_starts(n_cycles, params.period_s, durations_s)
    mech = params.mechanics
    if start == "periodic":
        vol, flo = periodic_response(starts[1] - starts[0], mech, params.insp_fraction, params.decay)
        y0 = np.array([vol[0] @ params.a, flo[0] @ params.a])
    else:
        y0 = np.zeros(2)
    t_out = _output_grid(starts, fs_hz)
    v_out, f_out, p_out = (np.full_like(t_out, np.nan) for _ in range(3))
    for c in range(starts.size - 1):
        y0 = _integrate_cycle(params, starts, c, y0, t_out, (v_out, f_out, p_out), rtol, atol)
    if mech.inertance == 0:
        f_out = (p_out - mech.elastance * v_out) / mech.resistance
    return BreathingCurve(t_out, params.relaxation_ml + 1000.0 * v_out, 1000.0 * f_out, p_out,
                          meta={"params": params.as_dict(), "cycle_starts_s": starts.tolist()})


def simulate_pressure(t_s, pressure_fn, mechanics: Mechanics, v0_l: float = 0.0, flow0_l_s: float = 0.0,
                      rtol: float = 1e-9, atol: float = 1e-12) -> tuple[np.ndarray, np.ndarray]:
    """Integrate I·V'' + R·V' + E·V = P(t) for an arbitrary pressure ``pressure_fn(t) -> cmH2O``.

    t_s : (n,) float, s, increasing. Returns (volume (n,) L above V_r, flow (n,) L/s).
    """

    t = np.asarray(t_s, dtype=float)
    e, r, inert = mechanics.elastance, mechanics.resistance, mechanics.inertance
    if inert > 0:
        def rhs(tt, y):
            return [y[1], (pressure_fn(tt) - e * y[0] - r * y[1]) / inert]
        y0 = [v0_l, flow0_l_s]
    else:
        def rhs(tt, y):
            return [(pressure_fn(tt) - e * y[0]) / r]
        y0 = [v0_l]
    sol = solve_ivp(rhs, (t[0], t[-1]), y0, method="Radau", t_eval=t, rtol=rtol, atol=atol,
                    max_step=(t[-1] - t[0]) / 200.0)
    if not sol.success:
        raise ConvergenceError(f"ODE integration failed: {sol.message}")
    vol = sol.y[0]
    flow = sol.y[1] if inert > 0 else (np.array([pressure_fn(x) for x in t]) - e * vol) / r
    return vol, flow


# --------------------------------------------------------------------------- tidal volume
def scaled_to_tidal_volume(params: BreathingParams, tidal_volume_ml: float) -> BreathingParams:
    """Same pattern with a_2..a_5 scaled so the periodic tidal volume equals ``tidal_volume_ml``."""
    vol, _ = periodic_response(params.period_s, params.mechanics, params.insp_fraction, params.decay)
    a = params.a
    wave = vol[:, 1:] @ a[1:]
    vt = 1000.0 * np.ptp(wave)
    if vt <= 0:
        raise InputError("the control pattern produces no tidal volume (a_2..a_5 all zero?)")
    k = tidal_volume_ml / vt
    return replace(params, control=(a[0], *(a[1:] * k)))
