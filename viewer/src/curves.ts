// Breathing curves for the viewer: named cycle shapes (built in), sampled curves from the server's
// /presets.json, and the curve stored in the model's glb. A curve gives the volume of both lungs
// above end-exhale (mL) at time t; tidal volume and rate are controls applied on top of its shape.

export interface Curve {
  name: string;
  label: string;
  /** Native tidal volume (mL, peak to peak) and rate (breaths/min). */
  tidalMl: number;
  rateBpm: number;
  /** Duration (s) of one loop of the shape at its native rate. */
  loopS: number;
  /** Normalised shape over one loop: phase in [0, 1) -> [0, 1] (0 = end-exhale, 1 = end-inhale). */
  shape(phase: number): number;
  source: string;
}

const TWO_PI = 2 * Math.PI;

/** Half-cosine rise over the inspiratory fraction rho, then exponential (passive) expiration. */
function riseThenDecay(rho: number, tau: number) {
  const tail = Math.exp(-1 / tau);
  return (phase: number) => {
    if (phase < rho) return 0.5 * (1 - Math.cos((Math.PI * phase) / rho));
    const w = (phase - rho) / (1 - rho);
    return (Math.exp(-w / tau) - tail) / (1 - tail);
  };
}

/** Rise and fall as half cosines with inspiratory fraction rho (rho = 0.5: plain cosine). */
function halfCosines(rho: number) {
  return (phase: number) =>
    phase < rho
      ? 0.5 * (1 - Math.cos((Math.PI * phase) / rho))
      : 0.5 * (1 + Math.cos((Math.PI * (phase - rho)) / (1 - rho)));
}

function periodic(name: string, label: string, tidalMl: number, rateBpm: number,
                  shape: (p: number) => number, source: string): Curve {
  return { name, label, tidalMl, rateBpm, loopS: 60 / rateBpm, shape, source };
}

/** Built-in named cycle shapes (used when the server offers no /presets.json). */
export function builtinCurves(): Curve[] {
  return [
    periodic('cosine', 'Plain cycle (cosine, 500 mL, 4 s)', 500, 15,
      (p) => 0.5 * (1 - Math.cos(TWO_PI * p)), 'built-in: the export default'),
    periodic('paper', 'Paper (500 mL, 5 s inhalation)', 500, 6, halfCosines(0.5),
      'built-in: Santhanam et al. 2008 Sec. V, symmetric exhalation assumed'),
    periodic('quiet', 'Quiet (I:E 1:2, passive exhalation)', 500, 12, riseThenDecay(1 / 3, 0.25),
      'built-in: half-cosine inspiration, exponential expiration'),
    periodic('deep', 'Deep breathing (1500 mL)', 1500, 6, riseThenDecay(0.4, 0.3), 'built-in'),
    periodic('exercise', 'Exercise (1200 mL, 30/min)', 1200, 30, halfCosines(0.5), 'built-in'),
  ];
}

/** Count breaths in a sampled curve: upward crossings of its mid level (at least 1). */
export function countCycles(v: ArrayLike<number>): number {
  let lo = Infinity, hi = -Infinity;
  for (let i = 0; i < v.length; i++) { lo = Math.min(lo, v[i]); hi = Math.max(hi, v[i]); }
  const mid = 0.5 * (lo + hi);
  let n = 0;
  for (let i = 1; i < v.length; i++) if (v[i - 1] < mid && v[i] >= mid) n++;
  return Math.max(n, 1);
}

/** A curve from samples t_s (increasing) and volume_ml; loops over its whole duration. */
export function sampledCurve(name: string, label: string, t: number[], v: number[], source: string): Curve {
  if (t.length < 2 || t.length !== v.length) throw new Error(`curve ${name}: need >= 2 matching samples`);
  const t0 = t[0], dur = t[t.length - 1] - t0;
  if (!(dur > 0)) throw new Error(`curve ${name}: zero duration`);
  let lo = Infinity, hi = -Infinity;
  for (const x of v) { lo = Math.min(lo, x); hi = Math.max(hi, x); }
  const span = hi - lo || 1;
  const cycles = countCycles(v);
  const shape = (phase: number) => {
    const tt = t0 + phase * dur;
    let a = 0, b = t.length - 1;
    while (b - a > 1) { const m = (a + b) >> 1; if (t[m] <= tt) a = m; else b = m; }
    const f = (tt - t[a]) / (t[b] - t[a]);
    return ((1 - f) * v[a] + f * v[b] - lo) / span;
  };
  return { name, label, tidalMl: hi - lo, rateBpm: (60 * cycles) / dur, loopS: dur, shape, source };
}

/** Volume (mL, both lungs, above end-exhale) at time t for a curve played at tidal and rate. */
export function volumeAt(curve: Curve, t: number, tidalMl: number, rateBpm: number): number {
  const loop = curve.loopS * (curve.rateBpm / rateBpm);
  const phase = ((t / loop) % 1 + 1) % 1;
  return tidalMl * curve.shape(phase);
}

/** Duration (s) of one loop at the given rate. */
export function loopDuration(curve: Curve, rateBpm: number): number {
  return curve.loopS * (curve.rateBpm / rateBpm);
}
